"""anny shape ("phenotype") parameters from what a studio knows about an actor.

anny's phenotype values lie in [0, 1] and interpolate MakeHuman targets (``anny.models.model_data.
PHENOTYPE_VARIATIONS``): ``gender`` 0 = male, 1 = female; ``age`` anchors -1/3 newborn, 0 baby,
1/3 child, 2/3 young adult (~25 years), 1 old — so anny's default 0.5 is an adolescent and adult
actors default to :data:`ADULT_AGE`; ``height`` is *not* a stature in metres: the stature it gives
depends on gender and age, so :func:`shape_for_stature` solves for it.

Stature is the vertical extent of the rest mesh (sole to the top of the head), in metres.
"""

from __future__ import annotations

import torch

from dualhuman_builder.errors import BodyModelError

ADULT_AGE = 2.0 / 3.0
GENDER_VALUES = {"male": 0.0, "female": 1.0, "neutral": 0.5}


def gender_value(gender: str | float) -> float:
    """``"male"``, ``"female"``, ``"neutral"`` or a number in [0, 1] to anny's gender value."""
    if isinstance(gender, str):
        try:
            return GENDER_VALUES[gender.lower()]
        except KeyError:
            raise BodyModelError(f"gender must be one of {sorted(GENDER_VALUES)} or a number in [0, 1], got {gender!r}") from None
    g = float(gender)
    if not 0.0 <= g <= 1.0:
        raise BodyModelError(f"gender value must be in [0, 1], got {g}")
    return g


def stature(model, shape) -> float:
    """Standing height in metres of a body with phenotype ``shape``."""
    v = model.rest(shape).vertices[0, :, 1]
    return float(v.max() - v.min())


def shape_for_stature(
    model,
    stature_m: float,
    gender: str | float = "neutral",
    age: float = ADULT_AGE,
    muscle: float = 0.5,
    weight: float = 0.5,
    proportions: float = 0.5,
    tolerance_m: float = 5e-4,
) -> dict[str, float]:
    """Phenotype dict whose stature is ``stature_m`` (within ``tolerance_m``), by bisection on
    anny's ``height`` value. Raises :class:`BodyModelError` when the stature is out of reach."""
    if not (0.5 < stature_m < 2.6):
        raise BodyModelError(f"stature {stature_m} m is not a human height in metres")
    base = {"gender": gender_value(gender), "age": float(age), "muscle": float(muscle), "weight": float(weight), "proportions": float(proportions)}

    def at(h: float) -> float:
        with torch.no_grad():
            return stature(model, model.shape_tensor({**base, "height": h}))

    lo, hi = 0.0, 1.0
    s_lo, s_hi = at(lo), at(hi)
    if not s_lo - tolerance_m <= stature_m <= s_hi + tolerance_m:
        raise BodyModelError(
            f"stature {stature_m:.3f} m is outside what anny reaches for these settings "
            f"({s_lo:.3f}-{s_hi:.3f} m at gender={base['gender']}, age={base['age']:.2f})",
            fix="check the height is in metres, or adjust age/gender",
        )
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        s = at(mid)
        if abs(s - stature_m) <= tolerance_m:
            return {**base, "height": mid}
        if s < stature_m:
            lo = mid
        else:
            hi = mid
    return {**base, "height": 0.5 * (lo + hi)}
