"""benchmarks/savn_profile.py's readers: HLO op metadata and the trace's per-op times."""
from __future__ import annotations

import gzip
import importlib.util
import json
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "savn_profile.py"

HLO = """\
  %dot.12 = f32[64,1,512]{2,1,0} dot(%a, %b), lhs_batch_dims={0}, metadata={op_name="jit(chunk)/while/body/closed_call/transpose(jvp(vmap(NavModel.recur)))/lstm_0.recur/dot_general.3" stack_frame_id=4}
  ROOT %copy.7 = f32[6,64,1,128]{3,2,1,0} copy(%wrapped_broadcast.3)
  %param.1 = f32[3]{0} parameter(0)
"""


def load():
    spec = importlib.util.spec_from_file_location("savn_profile", BENCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_op_metadata_and_times_are_read_from_the_hlo_and_the_trace(tmp_path):
    sp = load()
    meta = sp.op_metadata(HLO)
    assert meta["dot.12"][0] == "f32[64,1,512]"
    assert meta["dot.12"][1].endswith("lstm_0.recur/dot_general.3")
    assert meta["copy.7"] == ("f32[6,64,1,128]", "")          # no metadata: empty op_name
    assert sp.short(meta["dot.12"][1]) == \
        "transpose(jvp(vmap(NavModel.recur)))/lstm_0.recur/dot_general"
    events = [{"ph": "X", "name": "dot.12", "dur": 1500}, {"ph": "X", "name": "dot.12",
                                                          "dur": 500},
              {"ph": "X", "name": "ThunkExecutor::Execute", "dur": 9000},   # not an op
              {"ph": "i", "name": "copy.7"}]                                # not a span
    trace = tmp_path / "plugins" / "profile" / "run"
    trace.mkdir(parents=True)
    with gzip.open(trace / "host.trace.json.gz", "wt") as f:
        json.dump({"traceEvents": events}, f)
    assert sp.op_times(str(tmp_path), meta) == {"dot.12": (2000, 2)}
