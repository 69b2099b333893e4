"""The reaction prior as a trainable model: :class:`ReactionPrior` (the module) and
:class:`ReactionPriorSpec` (``dualhuman train reaction-prior``).

Training runs two phases, as the paper does (§3.1, §3.4): ``vae`` trains the motion VAE on both
people's windows with ``L1 + lambda_dist * KL(q(z|x) || N(0, I))`` (lambda_dist = 1e-4; both terms are
means over their elements, MLD's convention); ``inn`` trains the generator with the VAE frozen, with
the prior loss ``KL[q(z_r | x_r) || G(q(z_a | x~_a))]`` where ``x~_a`` is the actor corrupted by the
visibility-driven noise of :mod:`.noise` and the target is the clean reactor's encoding. An invertible
generator is also trained in reverse, ``KL[q(z_a | x_a) || G^-1(q(z_r | x~_r))]`` (weight
``reverse_weight``), since swapping action and reaction keeps the interaction's meaning.

Representation (config ``representation``, :mod:`.representation`): ``"joints"`` (default), the 22
joints in the actor's window frame, or ``"features"``, the paper's 269-dim features of each person
in that frame; the VAE's reconstruction loss and the refinement's data term are taken in the
chosen representation's normalised units, and every figure on the joints they give back.

Ablations (the paper's Table 4 rows), all config switches:

- ``use_vae = false``: no motion VAE. The code of a window is fixed, not learned: the first
  ``dct_coeffs`` coefficients of a DCT along time of each normalised coordinate, with a constant
  spread (:class:`.vae.DCTCodec`); the generator maps the actor's coefficients to the reactor's and
  the refinement optimises coefficients. Only the ``inn`` phase runs.
- ``mapper = "mlp"``: the INN replaced by an MLP of the same width and depth (one direction).
- ``noise_augment = false``: the generator sees clean inputs in training (actors; reactors in reverse).

``vae_from``: a reaction-prior run folder whose trained motion VAE and normalisation this model
starts from; its ``vae`` phase is then skipped and only the generator trains. The generator
ablations of one training seed can so share the full model's VAE (the VAE does not depend on the
generator or on the noise augmentation), which isolates what they change and saves most of their
training. The run's checkpoint holds the VAE it started from, so the folder is read once, at the start.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import torch
from torch import nn

from dualhuman_builder.models.base import Phase
from dualhuman_builder.models.reaction_prior.inn import CouplingINN, MLPMapper
from dualhuman_builder.models.reaction_prior.noise import NoiseModel, corrupt, noise_model
from dualhuman_builder.models.motion_torch import recover_joints_torch, window_features
from dualhuman_builder.models.reaction_prior.representation import (REPRESENTATIONS, Normalizer, canonical_pair,
                                                                    check_fps, flat, rows, unflat)  # fmt: skip
from dualhuman_builder.models.reaction_prior.vae import DCTCodec, MotionVAE, kl_gauss

NAME = "reaction-prior"

#: Defaults sized for a CPU. The paper / MLD setting for a GPU: latent_dim 256, layers 9, ff 1024,
#: vae_steps and inn_steps for 4000 and 500 epochs of the data (paper §3.5). The generator's 5000 steps
#: of 32 windows are about the paper's 500 epochs for a few hundred sequences. The VAE's 6000 steps: its
#: training length is what limits refinement at this size (``benchmarks/probes/probe_prior_code.py``).
DEFAULTS: dict[str, Any] = {
    "window": 64,
    "representation": "joints",
    "features_fps": 20.0,
    "latent_dim": 64,
    "latent_tokens": 1,
    "layers": 2,
    "heads": 4,
    "ff": 128,
    "dropout": 0.1,
    "lambda_dist": 1e-4,
    "use_vae": True,
    "dct_coeffs": 8,
    "dct_log_std": 0.0,
    "mapper": "inn",
    "mapper_blocks": 4,
    "mapper_hidden": 128,
    "mapper_clamp": 2.0,
    "reverse_weight": 1.0,
    "noise_augment": True,
    "noise": NoiseModel().as_dict(),
    "stats_batches": 16,
    "vae_steps": 6000,
    "inn_steps": 5000,
    "lr": 1e-4,
    "weight_decay": 5e-4,
    "lambda_prior": 0.01,
    "refine_iterations": 100,
    "refine_lr": 0.05,
    "eval_refine_windows": 8,
    "eval_refine_iterations": 50,
    "eval_seed": 0,
    "vae_from": None,
}
#: Config keys that shape the motion VAE and its normalisation: a run given as ``vae_from`` must share them.
VAE_KEYS = ("window", "representation", "features_fps", "latent_dim", "latent_tokens", "layers", "heads", "ff", "dropout",
            "stats_batches")

class ReactionPrior(nn.Module):
    """Normaliser + motion code (VAE or, ablated, DCT) + generator (INN or, ablated, MLP).

    All tensors in normalised units unless named otherwise; windows ``(B, L, 22, 3)`` metres in the
    actor's window frame (:mod:`.representation`). The codec sees rows of the configured
    ``representation``: ``L`` rows of joints, or ``L - 1`` rows of the 269-dim features (computed at
    ``features_fps``, the export's frame rate)."""

    def __init__(self, config: dict[str, Any]):
        super().__init__()
        c = self.config = {**DEFAULTS, **config}  # losses and evaluate read loss weights and noise from it
        self.window = int(c["window"])
        self.representation = str(c["representation"])
        if self.representation not in REPRESENTATIONS:
            raise ValueError(f"representation must be one of {', '.join(REPRESENTATIONS)}, got {self.representation!r}")
        self.fps = float(c["features_fps"])
        if not self.fps > 0:
            raise ValueError(f"features_fps must be a positive frame rate, got {c['features_fps']!r}")
        feats = REPRESENTATIONS[self.representation]
        self.norm = Normalizer(feats, int(c["stats_batches"]))
        if c["use_vae"]:
            self.codec: nn.Module = MotionVAE(feats, c["latent_dim"], c["layers"], c["heads"], c["ff"], c["dropout"],
                                              max_len=max(512, self.window), tokens=c["latent_tokens"])  # fmt: skip
        else:
            self.codec = DCTCodec(feats, rows(self.representation, self.window), c["dct_coeffs"], c["dct_log_std"])
        dim = 2 * self.codec.code_dim
        if c["mapper"] == "inn":
            self.mapper: nn.Module = CouplingINN(dim, c["mapper_blocks"], c["mapper_hidden"], c["mapper_clamp"])
        elif c["mapper"] == "mlp":
            self.mapper = MLPMapper(dim, c["mapper_blocks"], c["mapper_hidden"])
        else:
            raise ValueError(f"mapper must be 'inn' or 'mlp', got {c['mapper']!r}")
        if c.get("vae_from"):
            self._load_vae(Path(c["vae_from"]))

    def _load_vae(self, run_dir: Path) -> None:
        """Take the motion VAE and the normalisation of the reaction-prior run ``run_dir`` (its last
        checkpoint, after its ``vae`` phase), refusing a run whose VAE is shaped otherwise."""
        from dualhuman_builder.errors import DualhumanError
        from dualhuman_builder.models import runs

        fix = "pass vae_from a reaction-prior run (with the motion VAE) that finished its vae phase, with the same " + \
            ", ".join(VAE_KEYS)  # fmt: skip
        if not self.config["use_vae"]:
            raise DualhumanError("vae_from needs use_vae = true (the ablation without the VAE has none to take)", fix=fix)
        doc = runs.read_json(run_dir / runs.CONFIG, "the run's config")
        theirs = {**DEFAULTS, **(doc.get("config") or {})}
        if doc.get("model") != NAME or not theirs["use_vae"]:
            raise DualhumanError(f"{run_dir} is not a run of the reaction prior with its motion VAE", fix=fix)
        differ = [k for k in VAE_KEYS if theirs[k] != self.config[k]]
        if differ:
            raise DualhumanError(f"{run_dir}'s VAE differs from this config in " + ", ".join(
                f"{k} ({theirs[k]!r} there, {self.config[k]!r} here)" for k in differ), fix=fix)  # fmt: skip
        last, weights, _ = runs.load_checkpoint(run_dir, "cpu", optimizer=False)
        if last.get("phase") == "vae" and int(last.get("phase_step", 0)) < int(theirs["vae_steps"]):
            raise DualhumanError(f"{run_dir} has not finished its vae phase (step {last.get('phase_step')} of "
                                 f"{theirs['vae_steps']})", fix=fix)  # fmt: skip
        part = {k: v for k, v in weights.items() if k.startswith(("codec.", "norm."))}
        self.load_state_dict({**self.state_dict(), **part})

    @property
    def code_dim(self) -> int:
        """Numbers in a window's code (``mu``'s width): the VAE's tokens x latent_dim, or the DCT's coefficients."""
        return self.codec.code_dim

    def rows(self, joints: torch.Tensor) -> torch.Tensor:
        """Canonical joints ``(B, L, 22, 3)`` metres -> the representation's rows ``(B, R, F)``, not normalised."""
        return window_features(joints, self.fps) if self.representation == "features" else flat(joints)

    def decode_rows(self, z: torch.Tensor, length: int) -> torch.Tensor:
        """Code ``(B, D)`` -> normalised rows ``(B, R, F)`` of a window of ``length`` frames."""
        return self.codec.decode(z, rows(self.representation, length))

    def encode(self, joints: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Canonical joints ``(B, L, 22, 3)`` metres -> ``(mu, log sigma)`` each ``(B, D)``."""
        mu, logvar = self.codec.encode(self.norm(self.rows(joints)))
        return mu, 0.5 * logvar

    def decode(self, z: torch.Tensor, length: int | None = None) -> torch.Tensor:
        """Code ``(B, D)`` -> canonical joints ``(B, L, 22, 3)`` metres."""
        x = self.norm.inverse(self.decode_rows(z, length or self.window))
        return recover_joints_torch(x, world_from="mean") if self.representation == "features" else unflat(x)

    def react(self, mu_a: torch.Tensor, logstd_a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The prior on the reactor's code given the actor's: ``(mu~_r, log sigma~_r)``."""
        return self.mapper(torch.cat([mu_a, logstd_a], dim=-1)).chunk(2, dim=-1)

    def act(self, mu_r: torch.Tensor, logstd_r: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The reverse direction (INN only): the actor's code given the reactor's."""
        return self.mapper.inverse(torch.cat([mu_r, logstd_r], dim=-1)).chunk(2, dim=-1)


def _pair(batch: dict[str, Any]) -> tuple[torch.Tensor, ...]:
    """``(actor, reactor, origin, yaw)`` of a batch in the actor's window frame (:mod:`.representation`)."""
    return canonical_pair(batch["joints_actor"].float(), batch["joints_reactor"].float())


class ReactionPriorSpec:
    """:class:`~dualhuman_builder.models.base.ModelSpec` of the reaction prior (see the module docstring)."""

    name = NAME
    init_keys = ("vae_from",)  # a run's checkpoint holds the VAE it started from
    about = ("the Dual-Human paper's reaction prior: a motion VAE and an invertible network from the actor's latent "
             "distribution to the reactor's, which refines a noisy reactor (`dualhuman refine`)")

    def default_config(self) -> dict[str, Any]:
        return {k: (dict(v) if isinstance(v, dict) else v) for k, v in DEFAULTS.items()}

    def build(self, config: dict[str, Any]) -> nn.Module:
        return ReactionPrior({**DEFAULTS, **config})

    def make_dataset(self, export_dir: str | Path, split: str, config: dict[str, Any], seed: int):
        """The shared loop's windows of motion, after checking the export's frame rate (:func:`check_fps`)."""
        from dualhuman_builder.models.training import motion_windows

        data = motion_windows(export_dir, split, config, seed)
        check_fps({**DEFAULTS, **config}, float(data.manifest.get("fps", 0.0)), str(export_dir))
        return data

    def phases(self, config: dict[str, Any]) -> list[Phase]:
        c = {**DEFAULTS, **config}
        lr, wd = float(c["lr"]), float(c["weight_decay"])
        out = [Phase("vae", int(c["vae_steps"]), lr, wd)] if c["use_vae"] and not c.get("vae_from") else []
        return out + [Phase("inn", int(c["inn_steps"]), lr, wd)]

    def parameters(self, module: nn.Module, phase: str) -> Iterable[nn.Parameter]:
        if phase == "vae":
            return list(module.codec.parameters())
        if phase == "inn":
            return list(module.mapper.parameters())
        raise ValueError(f"the reaction prior has phases 'vae' and 'inn', not {phase!r}")

    def losses(self, module: nn.Module, batch: dict[str, Any], phase: str) -> dict[str, torch.Tensor]:
        ca, cr, _, _ = _pair(batch)
        stats = module.training and int(module.norm.ready) < module.norm.batches
        if stats or phase == "vae":
            both = module.rows(torch.cat([ca, cr], dim=0))
            if stats:
                module.norm.observe(both)
        if phase == "vae":
            x = module.norm(both)
            mu, logvar = module.codec.encode(x)
            z = mu + torch.randn_like(mu) * torch.exp(0.5 * logvar)
            x_hat = module.codec.decode(z, x.shape[1])
            l1 = (x_hat - x).abs().mean()
            kl = (0.5 * (mu**2 + torch.exp(logvar) - 1.0 - logvar)).mean()
            return {"loss": l1 + float(module.config["lambda_dist"]) * kl, "l1": l1.detach(), "kl": kl.detach()}
        if phase != "inn":
            raise ValueError(f"the reaction prior has phases 'vae' and 'inn', not {phase!r}")
        cfg = module.config
        was = module.codec.training
        module.codec.eval()  # frozen: no dropout, no gradient
        try:
            with torch.no_grad():
                na, nr = ca, cr
                if module.training and cfg["noise_augment"]:
                    nm = noise_model(cfg)
                    na = corrupt(ca, batch["visibility_actor"].to(ca), nm)
                    nr = corrupt(cr, batch["visibility_reactor"].to(cr), nm)
                mu_a, ls_a = module.encode(ca)
                mu_r, ls_r = module.encode(cr)
                mu_na, ls_na = module.encode(na)
                mu_nr, ls_nr = module.encode(nr)
        finally:
            module.codec.train(was)
        pm, pl = module.react(mu_na, ls_na)
        forward = kl_gauss(mu_r, ls_r, pm, pl).mean()
        out = {"prior_kl": forward.detach()}
        loss = forward
        w = float(cfg["reverse_weight"])
        if module.mapper.invertible and w > 0:
            qm, ql = module.act(mu_nr, ls_nr)
            reverse = kl_gauss(mu_a, ls_a, qm, ql).mean()
            out["reverse_kl"] = reverse.detach()
            loss = loss + w * reverse
        out["loss"] = loss
        return out

    def evaluate(self, module: nn.Module, batches: Iterator[dict[str, Any]], device: torch.device) -> dict[str, float]:
        from dualhuman_builder.models.reaction_prior.refine import refine_windows

        cfg = module.config
        sums: dict[str, float] = {}
        n_win = 0
        refine_a, refine_r, refine_v = [], [], []
        for batch in batches:
            ca, cr, _, _ = _pair({k: (v.to(device) if torch.is_tensor(v) else v) for k, v in batch.items()})
            B = ca.shape[0]
            mu_a, ls_a = module.encode(ca)
            mu_r, ls_r = module.encode(cr)
            rec_a, rec_r = module.decode(mu_a, ca.shape[1]), module.decode(mu_r, cr.shape[1])
            pm, pl = module.react(mu_a, ls_a)
            gen = module.decode(pm, cr.shape[1])
            figures = {
                "recon_mpjpe_mm": 0.5 * (_mpjpe(rec_a, ca) + _mpjpe(rec_r, cr)),
                "generation_mpjpe_mm": _mpjpe(gen, cr),
                "generation_root_mm": _root(gen, cr),
                "prior_kl": kl_gauss(mu_r, ls_r, pm, pl).sum(-1),
            }
            for k, v in figures.items():
                sums[k] = sums.get(k, 0.0) + float(v.sum())
            n_win += B
            have = sum(len(x) for x in refine_a)
            if have < int(cfg["eval_refine_windows"]):
                take = int(cfg["eval_refine_windows"]) - have
                refine_a.append(batch["joints_actor"][:take].to(device).float())
                refine_r.append(batch["joints_reactor"][:take].to(device).float())
                refine_v.append(batch["visibility_reactor"][:take].to(device).float())
        if not n_win:
            return {}
        out = {k: v / n_win for k, v in sums.items()}
        out["windows"] = float(n_win)
        if refine_a:
            a, r, v = torch.cat(refine_a), torch.cat(refine_r), torch.cat(refine_v)
            g = torch.Generator(device=a.device).manual_seed(int(cfg["eval_seed"]))
            noisy = corrupt(r, v, noise_model(cfg), generator=g)
            refined = refine_windows(module, a, noisy, float(cfg["lambda_prior"]), int(cfg["eval_refine_iterations"]),
                                     float(cfg["refine_lr"]))  # fmt: skip
            out["refine_windows"] = float(len(a))
            out["refine_before_mpjpe_mm"] = float(_mpjpe(noisy, r).mean())
            out["refine_after_mpjpe_mm"] = float(_mpjpe(refined, r).mean())
            out["refine_before_root_mm"] = float(_root(noisy, r).mean())
            out["refine_after_root_mm"] = float(_root(refined, r).mean())
        return out


def _mpjpe(pred: torch.Tensor, true: torch.Tensor) -> torch.Tensor:
    """Per window ``(B,)``: mean joint distance in mm (absolute, in the shared frame: placement counts)."""
    return (pred - true).norm(dim=-1).mean(dim=(1, 2)) * 1000.0


def _root(pred: torch.Tensor, true: torch.Tensor) -> torch.Tensor:
    """Per window ``(B,)``: mean pelvis distance in mm."""
    return (pred[:, :, 0] - true[:, :, 0]).norm(dim=-1).mean(dim=1) * 1000.0

