#!/usr/bin/env python3
"""Parity of orgnav_jax's TPN head with the release's MetaMemoryGraphModel (xiaobaishu0097/
ECCV-VN, built from a git mirror with random weights AND random biases, hidden 512,
multi_heads 1).

    python experiments/parity_tpn.py [--mirror DIR] [--torch-python PY] [--tol 1e-4]

A missing mirror, a --torch-python that is not there or cannot import torch: one line,
exit 2, before anything runs (the CLIs' convention, orgnav_jax.errors.run_cli).

A development check beside the shared parity tool (which covers the navigation outputs;
its README asks for the TPN head's own): it needs a git mirror of the release (fetch
github:xiaobaishu0097/ECCV-VN; default ../.mirror/xiaobaishu0097+ECCV-VN/repo beside the
project, or PARITY_MIRROR) and a Python with torch (default the parity tool's venv,
/tmp/parity_venv, or PARITY_VENV); not part of CI. The release runs in that Python (this
script re-runs itself there with --torch OUT.npz): its LSTM is replaced by a stub that returns given outputs x_t, and an
episode is driven as its agent drives it (states_rep = the r_t it returned so far,
states_memory / action_memory = the state_memory / action_memory rows it returned,
action_probs = the previous step's policy probabilities, zeros at step 0), so meta_action
at every step comes from the release's own a3clstm. Then the mapped weights
(orgnav_jax.models.release.load("MetaMemoryGraphModel", ...)) run orgnav_jax's TPN on the same x_t and p_t, step by
step (tpn_step on a TPNMemory) and over the whole episode (TPN.__call__), and the worst
relative difference max|ours - release| / max|release| over all steps is reported.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from types import SimpleNamespace

import numpy as np

# This file runs in two Pythons: the release's side (--torch) in one with torch that may
# lack jax and orgnav_jax, the comparison in this project's. Only the standard library
# and numpy are imported here; each side imports its own inside its functions.

ROOT = Path(__file__).resolve().parents[1]
MIRROR = os.environ.get("PARITY_MIRROR",
                        str(ROOT.parent / ".mirror" / "xiaobaishu0097+ECCV-VN" / "repo"))
TORCH_PY = str(Path(os.environ.get("PARITY_VENV", "/tmp/parity_venv")) / "bin" / "python")
TOOLS = ROOT.parent / "shared" / "tools" / "parity"     # its check.py imports the release
H, A = 512, 6


def parity_tool():
    """The shared parity tool's check.py (TOOLS), loaded from its file."""
    spec = importlib.util.spec_from_file_location("parity_check", TOOLS / "check.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def torch_side(out: str, episodes: int, steps: int, seed: int, soft: bool, mirror: str):
    import torch                                    # (the release's side has torch)
    tmp = tempfile.mkdtemp()
    # git show the release's files, stub PIL; its `models` package importable after
    models, _, commit = parity_tool().import_release(mirror, Path(tmp))
    from models.metamemorygraphmodel import MetaMemoryGraphModel  # (the release's)
    args = SimpleNamespace(action_space=A, num_category=22, hidden_state_sz=H, multi_heads=1,
                           dropout_rate=0.25)
    torch.manual_seed(seed)
    tm = MetaMemoryGraphModel(args).eval()
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in tm.named_parameters():
            if name.endswith("bias"):
                p.copy_(0.3 * torch.randn(p.shape, generator=g))
            elif p.ndim == 1:                                  # LayerNorm weight
                p.copy_(1.0 + 0.3 * torch.randn(p.shape, generator=g))
        if soft:     # small r: soft attention, so that which 10 slots are read matters
            for name, p in tm.meta_current_state_embedding[4].named_parameters():
                p.mul_(0.02)

    class StubLSTM(torch.nn.Module):                            # returns the given x_t
        x = None

        def forward(self, emb, hc):
            return self.x.reshape(1, 1, H), hc

    sd = {k: v.detach().numpy().copy() for k, v in tm.state_dict().items()}   # the whole model
    tm.lstm = StubLSTM()
    rng = np.random.default_rng(seed)
    xs = np.tanh(rng.standard_normal((episodes, steps, H))).astype(np.float32)
    xs *= 0.02 if soft else 1.0
    pr = np.exp(2 * rng.standard_normal((episodes, steps, A)))
    pr = (pr / pr.sum(-1, keepdims=True)).astype(np.float32)
    meta = np.zeros((episodes, steps, A), np.float32)
    emb = torch.zeros(1, 7 * 7 * 64)
    hc = (torch.zeros(2, 1, H), torch.zeros(2, 1, H))
    with torch.no_grad():
        for e in range(episodes):
            state_reps, state_memory, action_memory = [], [], []
            for t in range(steps):
                tm.lstm.x = torch.from_numpy(xs[e, t])
                probs = torch.zeros(1, A) if t == 0 else torch.from_numpy(pr[e, t - 1])[None]
                srep = torch.stack(state_reps) if state_reps else torch.zeros(1, H)
                smem = torch.stack(state_memory) if state_memory else torch.zeros(1, H)
                amem = torch.stack(action_memory) if action_memory else torch.zeros(1, A)
                res = tm.a3clstm(emb, *hc, probs, srep, smem, amem)
                rep, s_out, a_out, meta_t = res[3], res[4], res[5], res[6]
                state_reps.append(rep.squeeze())
                if s_out is not None:
                    state_memory.append(s_out.squeeze())
                    action_memory.append(a_out.squeeze())
                meta[e, t] = meta_t.numpy()[0]
            assert len(state_memory) == steps - 1
    np.savez(out, xs=xs, probs=pr, meta=meta, commit=commit,
             **{"sd:" + k: v for k, v in sd.items()})


def mutants(net, variables, xs, pr, meta):
    """Sensitivity: the worst relative difference of some wrong heads (each should fail)."""
    import flax.linen as nn                         # (this project's side only: see the top)
    import jax                                      # (this project's side only)
    from orgnav_jax.models import tpn_net as tpn    # (this project's side only)
    E, T = xs.shape[:2]
    valid = np.ones((E, T), bool)
    scale = np.abs(meta).max()
    cases = {
        "top-9 instead of top-10": lambda: tpn.TPN(hidden=H, action_embed=A, top_k=9),
        "no ReLU on the action embedding": lambda: type("M", (tpn.TPN,), {
            "embed_probs": lambda self, p: self.prob_embed(p)})(hidden=H, action_embed=A),
        "no memory read (zeros)": lambda: type("M", (tpn.TPN,), {
            "__call__": lambda self, h, p, v: self._head(
                self.represent(h), jax.numpy.zeros(h.shape[:-1] + (H + A,)))})(
            hidden=H, action_embed=A),
        "no ReLU after the state residual": lambda: type("M", (tpn.TPN,), {
            "represent": lambda self, h: h + self.rep_norm_2(self.rep_2(nn.relu(
                self.rep_norm_1(self.rep_1(h)))))})(hidden=H, action_embed=A),
    }
    for name, make in cases.items():
        out = np.asarray(jax.jit(make().apply)(variables, xs, pr, valid))
        print(f"  mutant {name:34s}: {np.abs(out - meta).max() / scale:.2e}")


def jax_side(npz: str, tol: float) -> int:
    import jax                                      # (this project's side only: see the top)
    from orgnav_jax.models import release           # (this project's side only)
    from orgnav_jax.models import tpn_net as tpn    # (this project's side only)
    d = np.load(npz)
    sd = {k[3:]: d[k] for k in d.files if k.startswith("sd:")}
    xs, pr, meta = d["xs"], d["probs"], d["meta"]
    E, T = xs.shape[:2]
    loaded = release.load("MetaMemoryGraphModel", sd)
    net, variables = loaded.tpn, loaded.tpn_params
    like = jax.eval_shape(net.init, jax.random.PRNGKey(0), xs[:1, :1], pr[:1, :1],
                          np.ones((1, 1), bool))
    assert jax.tree_util.tree_structure(like) == jax.tree_util.tree_structure(variables)
    for a, b in zip(jax.tree_util.tree_leaves(like), jax.tree_util.tree_leaves(variables)):
        assert a.shape == b.shape, (a.shape, b.shape)
    step = jax.jit(lambda h, mem: tpn.tpn_step(net, variables, h, mem))
    mem = tpn.memory_init(E, T, H)
    stepwise = []
    for t in range(T):
        logits, r, mem, _ = step(xs[:, t], mem)
        stepwise.append(np.asarray(logits))
        mem = tpn.memory_record(mem, r, pr[:, t])
    stepwise = np.stack(stepwise, 1)
    whole = np.asarray(jax.jit(net.apply)(variables, xs, pr, np.ones((E, T), bool)))
    scale = np.abs(meta).max()
    report = {}
    for name, ours in (("step-wise", stepwise), ("whole-episode", whole)):
        per_step = np.abs(ours - meta).max(axis=(0, 2)) / scale
        report[name] = per_step
        print(f"{name:13s}: worst relative difference {per_step.max():.2e} "
              f"(step 0: {per_step[0]:.2e}, steps 1-10: {per_step[1:11].max():.2e}, "
              f"steps 11+ (top-10 of > 10 slots): {per_step[11:].max():.2e})")
    w = np.asarray(jax.jit(lambda h: net.apply(variables, h, method=net.represent))(xs))
    s = np.einsum("eth,eih->eti", w, w)[:, 11:, :10]     # scores of a late step's slots
    print(f"release {str(d['commit'])[:12]}, {E} episodes x {T} steps, max|release| "
          f"{scale:.3g}, logits spread per step {np.ptp(meta, -1).mean():.3g}, score "
          f"spread over slots {np.ptp(s, -1).mean():.3g} (softmax {'soft' if np.ptp(s, -1).mean() < 5 else 'near one-hot'})")
    mutants(net, variables, xs, pr, meta)
    worst = max(v.max() for v in report.values())
    print(("PASS" if worst <= tol else "FAIL") + f": worst {worst:.2e} (tol {tol:.0e})")
    return 0 if worst <= tol else 1


def check_torch_python(python: str) -> None:
    """`python` runs and imports torch; UserError naming it otherwise."""
    from orgnav_jax.errors import UserError         # (this project's side only: see the top)
    found = shutil.which(python)
    if found is None:
        raise UserError(f"--torch-python {python}: no such executable (expected a Python "
                        "with torch; default the parity tool's venv, or PARITY_VENV)")
    try:
        done = subprocess.run([found, "-c", "import torch"], capture_output=True, text=True,
                              timeout=300)
    except (OSError, subprocess.SubprocessError) as err:
        raise UserError(f"--torch-python {python}: cannot be run ({err})") from None
    if done.returncode:
        last = (done.stderr.strip().splitlines() or ["?"])[-1]
        raise UserError(f"--torch-python {python}: cannot import torch ({last})")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--torch", help=argparse.SUPPRESS)
    ap.add_argument("--mirror", default=MIRROR, help="git mirror of xiaobaishu0097/ECCV-VN")
    ap.add_argument("--torch-python", default=TORCH_PY, help="a Python with torch")
    ap.add_argument("--episodes", type=int, default=3)
    ap.add_argument("--steps", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--soft", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--tol", type=float, default=1e-4)
    a = ap.parse_args(argv)
    if a.torch:
        return torch_side(a.torch, a.episodes, a.steps, a.seed, a.soft, a.mirror)
    from orgnav_jax.errors import UserError         # (this project's side only: see the top)
    if not Path(a.mirror).is_dir() or subprocess.run(
            ["git", "-C", a.mirror, "rev-parse", "HEAD"], capture_output=True).returncode:
        raise UserError(f"--mirror {a.mirror}: no git mirror of the release there: fetch "
                        "github:xiaobaishu0097/ECCV-VN (or give --mirror DIR, PARITY_MIRROR)")
    check_torch_python(a.torch_python)
    rc = 0
    for soft in (False, True):
        print(("soft attention (small r)" if soft else "release-like weights") + ":")
        with tempfile.TemporaryDirectory() as tmp:
            out = str(Path(tmp) / "release.npz")
            done = subprocess.run([a.torch_python, __file__, "--torch", out, "--mirror",
                                   a.mirror, "--episodes", str(a.episodes), "--steps",
                                   str(a.steps), "--seed", str(a.seed)]
                                  + (["--soft"] if soft else []))
            if done.returncode:
                raise UserError(f"the release's side in {a.torch_python} failed (exit "
                                f"{done.returncode}; its output is above)")
            rc |= jax_side(out, a.tol)
    return rc


if __name__ == "__main__":
    if "--torch" in sys.argv:     # the release's side: a Python with torch, maybe no orgnav_jax
        sys.exit(main())
    from orgnav_jax.errors import run_cli           # (this project's side only: see the top)
    sys.exit(run_cli(main))
