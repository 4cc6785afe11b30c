"""How good the agent's perception is: the knobs of the global view and the detector.

AI2-THOR agents see a frozen ImageNet ResNet-18's 7x7 map of a 300x300 frame and a
Faster R-CNN's detections; the synthetic benchmark stands in for both with a ray caster
(global_view.py) and a detector model (detector.py). With every knob at its default
(`Perception()`) the stand-ins are as clean as the `small` preset has always had them,
bit for bit; the `calibrated` preset (presets.py) degrades them towards what the real
networks deliver, chosen so that the rows without the method (WE, the Baseline) score on
val what they score in AI2-THOR (docs/calibrated.md).

Knob (default)            what it imitates
global_labels ("objects")  what a 7x7 ResNet cell says of what it sees: "objects" = the
                           hit object's category and furniture kind (exact labels);
                           "furniture" = furniture kind only; "none" = neither (geometry:
                           what kind of surface was hit, and its depth)
global_noise (0)           per-state noise on the global code (std, code units): features
                           vary with view, lighting and texture, not only with content
room_style (0)             per-room offset of the global code (std): a room's materials
                           and lighting shift every feature of it; unseen rooms look new
detect_range_scale (1)     scales each category's detection range (recall falls with
                           distance and size as a Faster R-CNN's does at 300x300)
peak_recall (0.95)         detection probability right in front of an object
min_box_area (4)           boxes smaller than this (pixels^2) are never detected
false_positive_rate (0.01) per state and category
fp_confidence_max (0.35)   false positives' confidence ~ U(0.05, max): high = not
                           separable from true detections by confidence
confidence_noise (0.08)    std of the true detections' confidence (calibration)
confusion (0)              probability that a detection carries the label of a similar
                           category (CONFUSABLE groups)
box_jitter (0)             std of the box corners (pixels)
appearance_noise (0.5)     view-dependent noise of the appearance code (the class
                           prototype's weight is fixed)
"""

from __future__ import annotations

import dataclasses
import numbers

import numpy as np

from orgnav_jax.constants import CATEGORIES, IMAGE_SIZE

GLOBAL_LABELS = ("objects", "furniture", "none")

# Categories a detector at 300x300 mistakes for one another (similar shape and size).
CONFUSABLE: tuple[tuple[str, ...], ...] = (
    ("Bowl", "Plate", "Pot", "Pan"),
    ("CellPhone", "RemoteControl", "AlarmClock"),
    ("Book", "Laptop"),
    ("DeskLamp", "FloorLamp"),
    ("Kettle", "CoffeeMachine", "Toaster"),
    ("Microwave", "Television"),
    ("Sink", "StoveBurner"),
)

# (low, high) of each numeric knob, both inclusive.
RANGES: dict[str, tuple[float, float]] = {
    "global_noise": (0.0, 10.0),
    "room_style": (0.0, 10.0),
    "detect_range_scale": (0.05, 4.0),
    "peak_recall": (0.0, 1.0),
    "min_box_area": (0.0, float(IMAGE_SIZE) ** 2),
    "false_positive_rate": (0.0, 1.0),
    "fp_confidence_max": (0.06, 0.99),
    "confidence_noise": (0.0, 1.0),
    "confusion": (0.0, 1.0),
    "box_jitter": (0.0, float(IMAGE_SIZE)),
    "appearance_noise": (0.0, 10.0),
}


@dataclasses.dataclass(frozen=True)
class Perception:
    """The perception knobs (module docstring); defaults = the `small` preset's."""
    global_labels: str = "objects"
    global_noise: float = 0.0
    room_style: float = 0.0
    detect_range_scale: float = 1.0
    peak_recall: float = 0.95
    min_box_area: float = 4.0
    false_positive_rate: float = 0.01
    fp_confidence_max: float = 0.35
    confidence_noise: float = 0.08
    confusion: float = 0.0
    box_jitter: float = 0.0
    appearance_noise: float = 0.5

    def __post_init__(self):
        if not isinstance(self.global_labels, str) or self.global_labels not in GLOBAL_LABELS:
            raise ValueError(f"perception knob global_labels {self.global_labels!r}, "
                             f"expected one of {list(GLOBAL_LABELS)}")
        for name, (lo, hi) in RANGES.items():
            v = getattr(self, name)
            # any real number (numpy's too: np.float32(0.2)), kept as a Python float so
            # that a set's info and the cache's comparison (cache.py) see plain numbers
            if isinstance(v, bool) or not isinstance(v, numbers.Real) \
                    or not lo <= float(v) <= hi:
                raise ValueError(f"perception knob {name} {v!r}, expected a number in "
                                 f"[{lo:g}, {hi:g}]")
            object.__setattr__(self, name, float(v))

    def changed(self) -> dict:
        """The knobs that differ from the defaults (for a set's info and the docs)."""
        base = Perception()
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                if getattr(self, f.name) != getattr(base, f.name)}


def parse_knobs(items: list[str] | None) -> dict:
    """["global_noise=0.5", "global_labels=none", ...] -> {name: value}, values typed as
    the Perception fields are; a one-line ValueError names a bad item, or a knob given
    twice (the last was taken silently)."""
    fields = {f.name for f in dataclasses.fields(Perception)}
    out, given = {}, {}
    for item in items or ():
        name, sep, value = item.partition("=")
        if not sep or name not in fields:
            raise ValueError(f"perception knob {item!r}: expected NAME=VALUE with NAME one "
                             f"of {sorted(fields)}")
        if name in given:
            raise ValueError(f"perception knob {name} given twice ({given[name]!r}, "
                             f"{item!r}): expected each knob once")
        given[name] = item
        if name == "global_labels":
            out[name] = value
            continue
        try:
            out[name] = float(value)
        except ValueError:
            raise ValueError(f"perception knob {item!r}: {value!r} is not a number") from None
    return out


def degrade_global(codes: np.ndarray, p: Perception, rng: np.random.Generator) -> np.ndarray:
    """The ray caster's codes (S, 7, 7, 12) of one room -> what `p` lets through.

    Channels: 0-4 hit kind one-hot, 5 depth, 6-8 furniture embedding, 9-11 object
    category embedding (global_view.py). Draws from `rng` only for nonzero noise; with
    the defaults the codes come back as they are."""
    if (p.global_labels, p.room_style, p.global_noise) == ("objects", 0.0, 0.0):
        return codes
    out = np.array(codes, np.float32)
    if p.global_labels != "objects":
        out[..., 9:12] = 0.0
    if p.global_labels == "none":
        out[..., 6:9] = 0.0
    if p.room_style > 0:
        out += rng.normal(0, p.room_style, out.shape[-1]).astype(np.float32)
    if p.global_noise > 0:
        out += rng.normal(0, p.global_noise, out.shape).astype(np.float32)
    return out


def confusion_partners(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, C): for each of n states and each category, a random other member of its
    CONFUSABLE group (the category itself if it has no group)."""
    index = {c: i for i, c in enumerate(CATEGORIES)}
    partner = np.tile(np.arange(len(CATEGORIES)), (n, 1))
    for group in CONFUSABLE:
        for c in group:
            others = np.array([index[o] for o in group if o != c])
            partner[:, index[c]] = others[rng.integers(len(others), size=n)]
    return partner


def degrade_detections(det_box: np.ndarray, det_conf: np.ndarray, code: np.ndarray,
                       p: Perception, rng: np.random.Generator
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Confusions and box jitter on one room's detections (S, C, 4), (S, C), (S, C, Da);
    the other detector knobs act inside detector.detect. A confused detection moves to
    its partner category's row unless that row holds a more confident detection. With
    neither knob set the arrays come back as they are, and `rng` is not drawn from."""
    if p.confusion == 0 and p.box_jitter == 0:
        return det_box, det_conf, code
    det_box, det_conf, code = det_box.copy(), det_conf.copy(), code.copy()
    S, C = det_conf.shape
    if p.confusion > 0:
        flip = (det_conf > 0) & (rng.random((S, C)) < p.confusion)
        partner = confusion_partners(rng, S)
        for s, c in zip(*np.nonzero(flip)):
            d = partner[s, c]
            if d == c or det_conf[s, d] >= det_conf[s, c]:
                continue
            det_box[s, d], det_conf[s, d], code[s, d] = det_box[s, c], det_conf[s, c], code[s, c]
            det_box[s, c], det_conf[s, c], code[s, c] = 0.0, 0.0, 0.0
    if p.box_jitter > 0:
        jitter = rng.normal(0, p.box_jitter, det_box.shape).astype(np.float32)
        box = np.clip(det_box + jitter, 0, IMAGE_SIZE)
        lo, hi = np.minimum(box[..., :2], box[..., 2:]), np.maximum(box[..., :2], box[..., 2:])
        box = np.concatenate([lo, hi], -1)
        det_box = np.where((det_conf > 0)[..., None], box, 0.0).astype(np.float32)
    return det_box, det_conf, code
