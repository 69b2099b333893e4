"""`dualhuman annotate` and `dualhuman export`: labels and the training-ready dataset."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click

from dualhuman_builder.cli.app import console, err_console, main


@main.group()
def annotate():
    """Interaction labels and descriptions: round-trip them through any annotation tool.

    \b
      dualhuman annotate vocabulary [WS]       the label names you may use
      dualhuman annotate export WS labels.csv  every take and sequence, to fill in
      dualhuman annotate import WS labels.csv  read them back (CSV or JSON Lines)

    A label record: labels from the vocabulary (CHI3D's eight types and NTU-120's mutual actions,
    extended by WS/labels.toml), actor and reactor for one-sided interactions, a symmetric flag,
    several free-text descriptions, the annotator and the time. The export stores them per
    sequence (text.json, with a multi-hot vector over labels.json).
    """


@annotate.command("vocabulary")
@click.argument("workspace", required=False, type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="Print labels.json as the export writes it.")
def annotate_vocabulary(workspace: Path | None, as_json: bool):
    """List the interaction labels (the built-in vocabulary, plus WORKSPACE/labels.toml if given).

    Example:  dualhuman annotate vocabulary WS
    """
    from dualhuman_builder.errors import WorkspaceError
    from dualhuman_builder.labels import load_vocabulary

    try:
        vocab = load_vocabulary(workspace)
    except ValueError as e:
        raise WorkspaceError(str(e), path=workspace) from None
    if as_json:
        click.echo(json.dumps(vocab.as_dict(), indent=1))
        return
    for i, lab in enumerate(vocab.labels):
        side = "one-sided" if lab.one_sided else "symmetric"
        console.print(f"{i:3d}  {lab.name:<20} {side:<10} {lab.description}  [dim]({', '.join(lab.sources)})[/]",
                      highlight=False, soft_wrap=True)  # fmt: skip


@annotate.command("export")
@click.argument("workspace", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.argument("file", required=False, type=click.Path(dir_okay=False, path_type=Path))
@click.option("--format", "fmt", type=click.Choice(["csv", "jsonl"]), default=None,
              help="File format (default: from FILE's extension; JSON Lines on standard output).")
@click.option("--no-blank", is_flag=True, help="Only stored annotations, no blank rows for unannotated takes.")
def annotate_export(workspace: Path, file: Path | None, fmt: str | None, no_blank: bool):
    """Write the annotations of WORKSPACE to FILE (.csv or .jsonl; standard output without FILE):
    every stored annotation, and a blank row for each take and sequence that has none yet, to be
    filled in and imported back.

    CSV columns: take, sequence, labels (';'-separated), actor, reactor, symmetric, annotator,
    annotated_at, text_1, text_2, text_3, ...

    Example:  dualhuman annotate export WS labels.csv
    """
    from dualhuman_builder.export.annotate import export_annotations
    from dualhuman_builder.workspace import Workspace

    with Workspace.open(workspace, readonly=True) as ws:
        text, n = export_annotations(ws, file, fmt, blank=not no_blank)
    if file is None:
        click.echo(text, nl=False)
    else:
        console.print(f"{n} row(s) written to {file}", highlight=False)


@annotate.command("import")
@click.argument("workspace", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.argument("file", type=click.Path(dir_okay=False, exists=True, path_type=Path))
@click.option("--annotator", default=None, help="Annotator name for rows whose annotator column is empty.")
@click.option("--skip-invalid", is_flag=True, help="Import the valid rows and list the invalid ones (default: import nothing).")
def annotate_import(workspace: Path, file: Path, annotator: str | None, skip_invalid: bool):
    """Read annotations from FILE (.csv or .jsonl, UTF-8) into WORKSPACE's catalog.

    The whole file is checked first: takes and sequences exist, labels are in the vocabulary,
    actor and reactor are actors of the take, the text is UTF-8, annotated_at is ISO 8601, names
    hold no control characters. A cell written as '=... (a formula escaped by `annotate export`)
    is read back without its leading '. A row replaces the stored
    annotation of the same take, sequence and annotator; blank rows are skipped. The next
    `dualhuman export` carries the labels into the dataset.

    Example:  dualhuman annotate import WS labels.csv --annotator alice
    """
    from rich.markup import escape

    from dualhuman_builder.export.annotate import import_annotations
    from dualhuman_builder.workspace import Workspace

    with Workspace.open(workspace) as ws:
        res = import_annotations(ws, file, annotator=annotator, skip_invalid=skip_invalid)
    for line, msg in res["invalid"]:  # the message quotes the file's text: never markup
        console.print(f"[yellow]skipped[/] line {line}: {escape(msg)}", highlight=False, soft_wrap=True)
    console.print(f"{res['imported']} annotation(s) imported from {escape(str(file))} ({res['blank']} blank, "
                  f"{len(res['invalid'])} invalid row(s) skipped)", highlight=False)  # fmt: skip


class _ExportGroup(click.Group):
    """`dualhuman export WS OUT` builds; `dualhuman export verify|shards ...` are subcommands."""

    def resolve_command(self, ctx, args):
        if args and args[0] not in self.commands and not args[0].startswith("-"):
            args = ["build", *args]
        return super().resolve_command(ctx, args)


@main.group(cls=_ExportGroup)
def export():
    """The training-ready dataset: build it, verify it, shard it, convert it.

    \b
      dualhuman export WS OUT               the fitted takes of WS -> dataset OUT
      dualhuman export verify OUT           checksums, schema, splits, NaNs
      dualhuman export shards OUT DIR       WebDataset tar shards of a split
      dualhuman export interhuman OUT DEST  InterGen's InterHuman layout (30 fps)
      dualhuman export humanml3d OUT DEST   HumanML3D's layout (20 fps)
      dualhuman export import-humanml3d SRC OUT   a HumanML3D folder -> dataset
      dualhuman export import-interhuman SRC OUT  an InterHuman folder -> dataset
    """


@export.command("build")
@click.argument("workspace", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.argument("out", type=click.Path(file_okay=False, path_type=Path))
@click.option("--take", "takes", multiple=True, help="Export only this take (repeatable; default: every fitted take).")
@click.option("--split", "split_ratio", type=click.FloatRange(min=0.0, max=1.0, min_open=True), default=0.75,
              show_default=True, help="Share of sequences in the train split (the rest is test).")
@click.option("--subject-disjoint", is_flag=True, help="No performer in both splits.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the split.")
@click.option("--strict", is_flag=True, help="Fail when a take lacks a stage instead of exporting what is complete.")
@click.option("--include-flagged", is_flag=True,
              help="Export takes the quality gates flagged (`dualhuman gates`) too; by default they are left out.")
@click.option("--synth-split", is_flag=True,
              help="Keep the train/test split of the workspace's synthetic-dataset plan (WS/synth.json: its held-out "
                   "actors and types); the other takes' split is drawn as usual.")
def export_build(workspace: Path, out: Path, takes: tuple[str, ...], split_ratio: float, subject_disjoint: bool, seed: int,
                 strict: bool, include_flagged: bool, synth_split: bool):  # fmt: skip
    """Export every fitted take of WORKSPACE as a dataset folder OUT.

    Per sequence: both actors' anny parameters and joints, the 269-dim motion features, contacts
    (bit-packed labels, distances, region events), labels and texts, cameras and renders; at the
    top a manifest (versions, units, axes, SHA-256 of every file), a schema of every array, seeded
    train/test splits, feature mean/std and a dataset card (README.md). Re-running completes a
    partial export and rewrites only what changed. Takes the quality gates flagged (`dualhuman
    gates WS`) are left out, each named with its flags, unless --include-flagged; the manifest's
    "quality" lists them.

    Example:  dualhuman export WS WS/export
    """
    from dualhuman_builder.export.collect import run_export
    from dualhuman_builder.workspace import Workspace

    splits = None
    if synth_split:
        from dualhuman_builder.sim.synth import load_plan, plan_splits

        plan = load_plan(workspace)
        if plan is None:
            raise click.UsageError(f"{workspace} has no synthetic-dataset plan (synth.json): --synth-split needs one "
                                   "made by `dualhuman synth`")  # fmt: skip
        splits = plan_splits(plan) or None
    with Workspace.open(workspace, readonly=True) as ws:
        m = run_export(ws, out, list(takes) or None, strict=strict, split_ratio=split_ratio,
                       subject_disjoint=subject_disjoint, seed=seed, log=console.print,
                       include_flagged=include_flagged, splits=splits)  # fmt: skip
    console.print(f"exported {len(m['sequences'])} sequence(s) to {out}; check it with `dualhuman export verify {out}`",
                  highlight=False)  # fmt: skip


@export.command("verify")
@click.argument("out", type=click.Path(file_okay=False, exists=True, path_type=Path))
def export_verify(out: Path):
    """Check an exported dataset: every file's SHA-256 against the manifest, arrays against the
    schema (shapes, dtypes, no NaN), splits disjoint and complete, every sequence has what the
    manifest promises, nothing else in the export. Safe on a damaged or hostile export: reads only
    the files the manifest lists, inside OUT, with size caps; never unpickles. Exit status 1 when a
    problem is found.

    Example:  dualhuman export verify WS/export
    """
    from rich.markup import escape

    from dualhuman_builder.export.verify import verify_export

    problems = verify_export(out)
    for p in problems:  # names from the export: never markup, control characters shown escaped
        console.print(f"[red]problem[/]: {escape(p if p.isprintable() else repr(p))}", highlight=False, soft_wrap=True)
    if problems:
        sys.exit(1)
    console.print(f"[green]{escape(str(out))}: verified[/]", highlight=False)


@export.command("shards")
@click.argument("out", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.argument("shard_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option("--split", type=click.Choice(["train", "test", "all"]), default="train", show_default=True)
@click.option("--max-mb", type=click.FloatRange(min=0.001), default=256.0, show_default=True, help="Largest shard size (MiB).")
def export_shards(out: Path, shard_dir: Path, split: str, max_mb: float):
    """Write a split of the export OUT as WebDataset tar shards into SHARD_DIR (one sample per
    sequence: motion, contacts, events, text, cameras, keypoints).

    Example:  dualhuman export shards WS/export WS/shards --split train
    """
    from dualhuman_builder.export.shards import write_shards

    paths = write_shards(out, shard_dir, max_bytes=int(max_mb * 2**20), split=split)
    console.print(f"{len(paths)} shard(s) in {shard_dir}", highlight=False)


def _print_retarget(doc: dict) -> None:
    """The bone-length change of a retargeted conversion: overall, then each bone's ratio range."""
    rt = doc.get("retarget") or {}
    if rt.get("skeleton", "none") == "none" or not rt.get("per_bone"):
        return
    console.print(f"retargeted {rt['persons']} person(s) to the {rt['skeleton']} skeleton: bone length "
                  f"x{rt['ratio_min']:.3f} to x{rt['ratio_max']:.3f} (mean x{rt['ratio_mean']:.3f}), root path "
                  f"x{rt['root_scale_min']:.3f} to x{rt['root_scale_max']:.3f}; per bone, named by its end joint:",
                  highlight=False, soft_wrap=True)  # fmt: skip
    cells = [f"{name:<15}x{lo:.3f}" + (f"-{hi:.3f}" if hi - lo >= 5e-4 else "      ")
             for name, (lo, hi) in rt["per_bone"].items()]  # fmt: skip
    for k in range(0, len(cells), 3):
        console.print("  " + "  ".join(cells[k:k + 3]), highlight=False, soft_wrap=True)


def _convert(layout: str, out: Path, dest: Path, split: str, label_texts: bool, retarget: str = "none") -> None:
    from rich.markup import escape

    from dualhuman_builder.export import convert

    try:
        doc = getattr(convert, f"to_{layout}")(out, dest, split=split, label_texts=label_texts, retarget=retarget)
    except ValueError as e:
        raise click.UsageError(str(e)) from None
    c, unit = doc["counts"], "motions" if "motions" in doc else "sequences"
    per = f" = {doc['motions']} motions" if "motions" in doc else ""
    console.print(f"{layout}: {doc['sequences_converted']} sequence(s){per} ({c['train']} train, {c['test']} test {unit}), "
                  f"{len(doc['skipped'])} skipped, {len(doc['texts_from_labels'])} captioned from labels -> {dest}",
                  highlight=False, soft_wrap=True)  # fmt: skip
    _print_retarget(doc)
    for note in doc.get("notes", []):  # e.g. split lists filled because the export has too few sequences
        err_console.print(f"[yellow]note:[/] {escape(note)}", highlight=False, soft_wrap=True)


_CONVERT_OPTIONS = [
    click.argument("out", type=click.Path(file_okay=False, exists=True, path_type=Path)),
    click.argument("dest", type=click.Path(file_okay=False, path_type=Path)),
    click.option("--split", type=click.Choice(["all", "train", "test"]), default="all", show_default=True,
                 help="Convert only this split of the export."),
    click.option("--label-texts/--no-label-texts", default=True, show_default=True,
                 help="Caption a sequence without text from its labels ('two people interact: <label>.'); off: skip it."),
    click.option("--retarget", type=click.Choice(["none", "humanml3d", "interhuman"]), default="none",
                 show_default=True,
                 help="Give both persons a format's reference skeleton (each bone's direction kept per frame, its "
                      "length set; root path scaled by the leg ratio) and print the bone-length change. humanml3d: "
                      "HumanML3D's skeleton (subject 000021); interhuman: not available, no published bone lengths."),
]  # fmt: skip


def _with(options: list):
    """A decorator applying ``options`` (click decorators) in their listed order, so commands share them."""

    def apply(f):
        for deco in reversed(options):
            f = deco(f)
        return f

    return apply


_convert_options = _with(_CONVERT_OPTIONS)


@export.command("interhuman")
@_convert_options
def export_interhuman(out: Path, dest: Path, split: str, label_texts: bool, retarget: str):
    """Convert the export OUT to InterGen's InterHuman layout in DEST (30 fps), so InterGen's
    dataloader reads it unchanged (DATA_ROOT = DEST).

    Writes motions_processed/person1|person2/<id>.npy (InterHuman's raw (T, 492) per-frame joints and
    6D rotations, Z up, person a = person1), features/p1|p2/<id>.npy (the 262-dim features),
    annots/<id>.txt (three or more sentences), train/val/test.txt (also under split/; val = test),
    ignore_list.txt, global_mean/std.npy, and conversion.json (the per-sequence transform back to the
    world frame, skipped sequences with reasons).

    Example:  dualhuman export interhuman WS/export WS/interhuman
    """
    _convert("interhuman", out, dest, split, label_texts, retarget)


@export.command("humanml3d")
@_convert_options
def export_humanml3d(out: Path, dest: Path, split: str, label_texts: bool, retarget: str):
    """Convert the export OUT to HumanML3D's layout in DEST (20 fps, one motion per person: <id>_a,
    <id>_b), for single-person text-to-motion code (T2M, MDM, ...).

    Writes new_joint_vecs/<name>.npy (T-1, 263), new_joints/<name>.npy (T-1, 22, 3) canonical,
    texts/<name>.txt (caption#tokens#0.0#0.0; tokens are lowercased words tagged OTHER, not spaCy's
    lemmas and POS), Mean.npy/Std.npy over the train motions, train/val/test/all.txt (val = test),
    and conversion.json. With --retarget humanml3d every motion gets HumanML3D's reference bone
    lengths, so the vectors lie where HumanML3D's Mean/Std and the T2M evaluators expect them.

    Example:  dualhuman export humanml3d WS/export WS/humanml3d --retarget humanml3d
    """
    _convert("humanml3d", out, dest, split, label_texts, retarget)


def _import(layout: str, src: Path, out: Path, split_ratio: float, seed: int, keep_split: bool) -> None:
    from rich.markup import escape

    from dualhuman_builder.export import importers

    res = getattr(importers, f"import_{layout}")(src, out, split_ratio=split_ratio, seed=seed, keep_split=keep_split)
    c = res["manifest"]["counts"]
    console.print(f"{res['layout']}: {res['imported']} sequence(s) imported ({c['train']} train, {c['test']} test; "
                  f"{res['split_from_source']} split as the source lists them), {len(res['skipped'])} skipped -> {out}",
                  highlight=False, soft_wrap=True)  # fmt: skip
    for note in res.get("notes", []):
        err_console.print(f"[yellow]note:[/] {escape(note)}", highlight=False, soft_wrap=True)
    for name, why in res["skipped"].items():  # names and reasons come from the source folder: never markup
        err_console.print(f"[yellow]skipped[/] {escape(repr(name))}: {escape(why)}", highlight=False, soft_wrap=True)


_IMPORT_OPTIONS = [
    click.argument("src", type=click.Path(file_okay=False, exists=True, path_type=Path)),
    click.argument("out", type=click.Path(file_okay=False, path_type=Path)),
    click.option("--split", "split_ratio", type=click.FloatRange(min=0.0, max=1.0, min_open=True), default=0.75,
                 show_default=True, help="Share of the sequences that the source's split lists do not place (all of "
                 "them with --draw-split) in the export's train split."),
    click.option("--seed", type=int, default=0, show_default=True, help="Seed of the split."),
    click.option("--keep-source-split/--draw-split", "keep_split", default=True, show_default=True,
                 help="Keep the source's train/val/test.txt as the export's split (train -> train, val and test -> "
                 "test), or draw the split with --split and --seed."),
]  # fmt: skip


_import_options = _with(_IMPORT_OPTIONS)


@export.command("import-humanml3d")
@_import_options
def export_import_humanml3d(src: Path, out: Path, split_ratio: float, seed: int, keep_split: bool):
    """Import a folder in HumanML3D's layout (SRC) as a dataset export in OUT, to train the
    toolkit's models on it; the inverse of `dualhuman export humanml3d`.

    \b
    Reads, under SRC:
      new_joints/<name>.npy  (T, 22, 3) joints, metres, Y up, 20 fps, each
                             motion in its own canonical frame
      texts/<name>.txt       caption#tokens#from#to lines (captions kept)
      train/val/test.txt     the export's split (val, test -> test;
                             --draw-split to draw it), also kept in
                             sequence.json (meta.imported_from.split)

    The export holds pairs: motions <id>_a and <id>_b (as `dualhuman export humanml3d` names them)
    become sequence <id>; any other motion is skipped as unpaired and listed. HumanML3D keeps no
    relative placement, so both persons start at the origin facing +Z. Only joints are imported:
    the export's body model is "joints-only" (no pose or shape parameters); joints, features,
    texts and `dualhuman export verify` work as for any export. Sequences the split lists do not
    place are split with --split and --seed. Files that cannot be used (wrong shape, NaN, too large, a
    link out of SRC) are skipped with their reason.

    Example:  dualhuman export import-humanml3d ~/data/HumanML3D WS/hml-export
    """
    _import("humanml3d", src, out, split_ratio, seed, keep_split)


@export.command("import-interhuman")
@_import_options
def export_import_interhuman(src: Path, out: Path, split_ratio: float, seed: int, keep_split: bool):
    """Import a folder in InterHuman's layout (SRC, InterGen's DATA_ROOT) as a dataset export in
    OUT, to train the toolkit's models on it; the inverse of `dualhuman export interhuman`.

    \b
    Reads, under SRC:
      motions_processed/person1/<id>.npy  (T, 492) raw rows at 30 fps;
      motions_processed/person2/<id>.npy  columns 0:66 are the 22 body
                                          joints, metres, Z up (turned
                                          to Y up)
      annots/<id>.txt                     one description per line
      train/val/test.txt                  the export's split (val, test ->
                                          test; --draw-split to draw it)
      ignore_list.txt                     these ids are skipped
      conversion.json                     if SRC was written by `dualhuman
                                          export interhuman`: the joints go
                                          back to the original world frame

    person1 becomes person a, person2 person b, in their shared frame. Only joints are imported
    (body model "joints-only": no pose or shape parameters). Sequences the split lists do not place
    are split with --split and --seed. Files that cannot be used (wrong shape, NaN, too large, a link
    out of SRC, person2 missing) are skipped with their reason.

    Example:  dualhuman export import-interhuman ~/data/InterHuman WS/ih-export
    """
    _import("interhuman", src, out, split_ratio, seed, keep_split)
