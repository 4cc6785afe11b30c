"""A table's rows: the name `BASE+VARIANT@LR` taken apart once, into a Row.

    row = parse_row("org_il+tpn_all@1e-4")    # validated against ROWS and TPN_VARIANTS
    row.base, row.variant, row.lr             # "org_il", "tpn_all", "1e-4"
    row.test_time()                           # {"when": "all", "tpn_lr": 0.0001}

A row is a training preset (ROWS: the Tables' presets and VTNet's), `random` (the uniform
random policy), or BASE+VARIANT[@LR]: the TPN (stage 2) of row BASE's run evaluated with a
test-time variant (TPN_VARIANTS) at learning rate LR (the TPN config's default without
one). A row of PRETRAIN_ROWS pre-trains each seed first (VTNet, issue 43).
"""

from __future__ import annotations

import dataclasses

from orgnav_jax.training.config import TABLE_ROWS, VTNET_PRESETS

# the rows: the Tables' presets and VTNet's (issue 43)
ROWS: dict[str, dict] = {**TABLE_ROWS, **VTNET_PRESETS}
# test-time variants of a TPN row (TPNConfig fields)
TPN_VARIANTS: dict[str, dict] = {
    "tpn": {}, "tpn_all": {"when": "all"}, "tpn_random": {"target": "random"},
    "tpn_cosine": {"deadlock": "cosine", "placement": "state"},   # (release: visited only)
    "tpn_train_mode": {"tpn_train_mode": True}}   # the release's dropout confound
# rows whose A2C run starts from a supervised pre-training of the seed, as `--preset
# vtnet` does (the training CLI's list, train.PRETRAIN_PIPELINES; tests/test_claims.py
# keeps the two equal)
PRETRAIN_ROWS: tuple[str, ...] = ("vtnet",)
RANDOM = "random"


@dataclasses.dataclass(frozen=True)
class Row:
    """A row's name taken apart: base (a preset or `random`), variant (a TPN_VARIANTS key,
    None for a navigation row) and lr (the text after @, None without one)."""
    base: str
    variant: str | None = None
    lr: str | None = None

    @property
    def name(self) -> str:
        """The row's name as tables and specs write it."""
        if self.variant is None:
            return self.base
        return f"{self.base}+{self.variant}" + (f"@{self.lr}" if self.lr else "")

    @property
    def is_tpn(self) -> bool:
        return self.variant is not None

    @property
    def tpn_tag(self) -> str:
        """VARIANT[@LR]: the name of a TPN row's results file (test_<tag>.json)."""
        return self.name.partition("+")[2]

    @property
    def pretrains(self) -> bool:
        """Whether the base row's seeds are pre-trained first (PRETRAIN_ROWS)."""
        return self.base in PRETRAIN_ROWS

    def test_time(self) -> dict:
        """A TPN row's test-time fields: its variant's and, with @LR, tpn_lr."""
        return dict(TPN_VARIANTS[self.variant], **({"tpn_lr": float(self.lr)}
                                                   if self.lr else {}))

    @classmethod
    def of(cls, text: str) -> Row:
        """Take `text` apart as BASE[+VARIANT[@LR]], without checking the names (a row of
        a results file written before a preset was renamed still reads)."""
        base, plus, rest = text.partition("+")
        variant, at, lr = rest.partition("@")
        if not plus:
            base, at, lr = base.partition("@")
            if at:
                raise ValueError(f"row {text!r}: @LR follows a TPN variant (BASE+VARIANT@LR)")
        return cls(base, variant if plus else None, lr if at else None)


def parse_row(text: str) -> Row:
    """A row's name, checked: ROW (a ROWS name or random), or BASE+VARIANT[@LR] with
    VARIANT in TPN_VARIANTS, LR a number >= 0 and BASE not a SAVN row. ValueError naming
    the row otherwise."""
    expected = (f"unknown row {text!r}: expected one of {sorted(ROWS)}, or "
                f"BASE+VARIANT[@LR] with VARIANT in {sorted(TPN_VARIANTS)}")
    try:
        row = Row.of(text)
    except ValueError:
        raise ValueError(expected) from None
    ok = (row.base in ROWS or (row.base == RANDOM and not row.is_tpn)) and \
        (not row.is_tpn or row.variant in TPN_VARIANTS)
    try:
        ok = ok and (row.lr is None or float(row.lr) >= 0)
    except ValueError:
        ok = False
    if not ok:
        raise ValueError(expected)
    if row.is_tpn and ROWS[row.base].get("savn"):
        raise ValueError(f"row {text!r}: a SAVN run cannot be a TPN base (docs/savn.md)")
    return row


def all_row_names() -> list[str]:
    """Every row name without @LR: the presets and each TPN variant on each (--help)."""
    return sorted(ROWS) + [f"{b}+{v}" for b in sorted(ROWS) for v in TPN_VARIANTS]


def lr_tag(rows: list[str]) -> str:
    """The test-time learning rate tag of a table's TPN rows (the first @LR; 1e-3, the
    tag of the tables made before one was written, when none has one)."""
    tags = [Row.of(r).lr for r in rows if Row.of(r).lr]
    return tags[0] if tags else "1e-3"
