"""experiments/claims.py: paired-by-seed differences and verdicts on a hand-made table."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest


@pytest.fixture(scope="module")
def claims():
    path = Path(__file__).resolve().parents[1] / "experiments" / "claims.py"
    spec = importlib.util.spec_from_file_location("claims", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _row(*success):
    return {str(s): {"success": v} for s, v in enumerate(success)}


def test_paired_differences_verdicts_and_full_model(claims, tmp_path):
    results = {"baseline": _row(0.50, 0.60, 0.40), "il": _row(0.55, 0.62, 0.46),
               "org": _row(0.45, 0.61), "org_il": _row(0.70, 0.70, 0.70),
               "org_il+tpn@1e-3": _row(0.72, 0.69, 0.74),
               "org_il+tpn_random@1e-3": _row(0.73, 0.75, 0.80)}
    d, seeds = claims.paired(results, "il", "baseline")
    assert seeds == ["0", "1", "2"]
    assert d.tolist() == pytest.approx([5.0, 2.0, 6.0])
    d, seeds = claims.paired(results, "org", "baseline")       # only the shared seeds
    assert seeds == ["0", "1"] and d.tolist() == pytest.approx([-5.0, 1.0])
    path = tmp_path / "results.json"
    path.write_text(json.dumps(results))
    claims.main([str(path)])
    text = (tmp_path / "claims.md").read_text()
    assert "| IL > Baseline | +4.3 ± 1.7 | 0,1,2 | holds |" in text
    assert "| ORG > Baseline | -2.0 ± 3.0 | 0,1 | does not hold |" in text
    assert "| IL on every step < IL | not measured |" in text
    # random targets beat the TPN here: the claim fails, and the full model is not best
    assert "| TPN random target < TPN (ORG + IL) | +4.3 ± 2.4 | 0,1,2 | does not hold |" \
        in text
    assert "does not hold (best: org_il+tpn_random@1e-3)" in text
