"""Which generated images the default classifier adds: candidates and the choice on the validation split.

A *candidate* adds to the real training images at most ``ratio`` times as many generated ones per
class, chosen by ``filter``: ``all`` (a seeded random draw where the cap binds) or ``confident``
(those the real-only classifier gives their own class with probability at least ``confidence``,
most confident first). The *policy* compares each candidate with real only on the validation
images, paired image by image and averaged over seeds, with an interval that treats each split
group (instance, session, ...) as one unit, since images of one group are not independent, and
counting the spread between seeds. A candidate is chosen only when the lower end of its interval
of the gain is above zero (95% for all candidates together); the best such one wins. Otherwise, or without validation images, the policy is real only, so a user
who trusts the default is not made worse off beyond the noise of the choice.

Pure numpy: no torch, no files.
"""

from __future__ import annotations

import math
from statistics import NormalDist

import numpy as np

REAL_ONLY = "real"
FILTERS = ("all", "confident")
Z95 = 1.959964


def candidate_setting(ratio: float, filter_name: str) -> str:
    """The accuracy table's setting name of a candidate."""
    return f"real+generated ({filter_name}, ratio {ratio:g})"


def generated_subset(labels: np.ndarray, real_per_class: dict[int, int], ratio: float, filter_name: str, seed: int,
                     own_class_probability: np.ndarray | None = None, confidence: float = 0.5) -> np.ndarray:
    """Sorted indices of the generated images a candidate adds (see the module docstring).

    ``labels`` are the generated images' classes, ``real_per_class`` the number of real training
    images per class (the cap is ``floor(ratio * that)``), ``own_class_probability`` the real-only
    classifier's probability of each image's own class (needed by ``confident``)."""
    if filter_name not in FILTERS:
        raise ValueError(f"unknown generated-image filter {filter_name!r} (allowed: {', '.join(FILTERS)})")
    if filter_name == "confident" and own_class_probability is None:
        raise ValueError("the confident filter needs the real-only classifier's probabilities")
    rng = np.random.default_rng(seed)
    chosen = []
    for label in np.unique(labels):
        members = np.flatnonzero(labels == label)
        cap = int(math.floor(ratio * real_per_class.get(int(label), 0) + 1e-9))
        if filter_name == "confident":
            members = members[own_class_probability[members] >= confidence]
            members = members[np.argsort(-own_class_probability[members], kind="stable")][:cap]
        elif len(members) > cap:
            members = rng.choice(members, size=cap, replace=False)
        chosen.append(members)
    return np.sort(np.concatenate(chosen)).astype(int) if chosen else np.zeros(0, dtype=int)


def paired_difference(correct: np.ndarray, baseline: np.ndarray, groups: np.ndarray,
                      z: float = Z95) -> tuple[float, float, float]:
    """Mean accuracy gain of ``correct`` over ``baseline`` and its interval, paired image by image.

    Both are 0/1 (or shares) per image, shape ``images`` or ``seeds x images`` (the same seeds).
    The standard error adds two parts: the images', from the seed-averaged differences with each
    of ``groups`` as one unit (cluster-robust: the per-group sums vary around group size times the
    mean), and the training runs', the spread of the per-seed gains over the square root of the
    number of seeds (a classifier is a random draw too). With one group the interval is (-1, 1)."""
    a = np.atleast_2d(np.asarray(correct, dtype=float))
    b = np.atleast_2d(np.asarray(baseline, dtype=float))
    if a.shape != b.shape or a.shape[1] != len(groups):
        raise ValueError(f"paired_difference: {a.shape} and {b.shape} (seeds x images) but {len(groups)} groups")
    n = a.shape[1]
    if n == 0:
        return math.nan, math.nan, math.nan
    d = (a - b).mean(axis=0)
    mean = float(d.mean())
    _, inverse = np.unique(np.asarray(groups), return_inverse=True)
    g = inverse.max() + 1
    if g < 2:
        return mean, -1.0, 1.0
    sums = np.bincount(inverse, weights=d, minlength=g)
    sizes = np.bincount(inverse, minlength=g)
    images_var = g / (g - 1) * float(((sums - sizes * mean) ** 2).sum()) / n ** 2
    per_seed = (a - b).mean(axis=1)
    seeds_var = float(per_seed.var(ddof=1)) / len(per_seed) if len(per_seed) > 1 else 0.0
    se = math.sqrt(images_var + seeds_var)
    return mean, max(-1.0, mean - z * se), min(1.0, mean + z * se)


def family_z(candidates: int) -> float:
    """Two-sided normal quantile that keeps the chance of any of ``candidates`` intervals missing at 5%
    (Bonferroni): 1.96 for one, 2.24 for two."""
    return NormalDist().inv_cdf(1 - 0.025 / max(1, candidates))


def choose(val_correct: dict[str, np.ndarray], groups: np.ndarray, baseline: str = REAL_ONLY) -> dict:
    """The policy's choice among ``val_correct`` (setting -> 0/1 correctness, ``seeds x images``, on the
    validation images of ``groups``): ``{"chosen", "reason", "candidates": [...]}``, each candidate with
    its validation accuracy and the gain over ``baseline`` with its interval, 95% for the candidates
    together (:func:`family_z`; module docstring)."""
    base = np.atleast_2d(val_correct[baseline])
    rows, winners = [], []
    z = family_z(len(val_correct) - 1)
    for name, correct in val_correct.items():
        if name == baseline:
            continue
        gain, low, high = paired_difference(correct, base, groups, z)
        rows.append({"setting": name, "val_accuracy": round(float(np.mean(correct)), 6), "val_gain": round(gain, 6),
                     "val_gain_interval": [round(low, 6), round(high, 6)]})
        if low > 0:
            winners.append((gain, name))
    n, g = base.shape[1], len(np.unique(groups))
    if winners:
        gain, chosen = max(winners)
        reason = (f"'{chosen}' beat real only on the validation split by {gain:+.3f} accuracy, beyond its "
                  f"interval ({n} images in {g} groups)")
    else:
        chosen = baseline
        reason = (f"no candidate beat real only on the validation split beyond its interval ({n} images in "
                  f"{g} groups), so no generated images are added")
    return {"chosen": chosen, "reason": reason, "val_accuracy_real": round(float(base.mean()), 6), "candidates": rows}


def missing_validation(val_classes: list[str], classes: list[str]) -> str | None:
    """Why no validation-based choice is possible (a class without validation images), or None."""
    absent = [c for c in classes if c not in set(val_classes)]
    if not absent:
        return None
    shown = ", ".join(absent[:5]) + (f" and {len(absent) - 5} more" if len(absent) > 5 else "")
    return (f"{len(absent)} of {len(classes)} classes have no validation images ({shown}): the data has too few "
            f"groups (instances, sessions) for the pairs stage to hold out a validation split, so the policy "
            f"cannot be chosen and stays real only")
