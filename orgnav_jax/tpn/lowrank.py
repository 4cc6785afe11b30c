"""Per-episode fast weights as low-rank deltas: TPN's test-time update on many parameters.

One single-example SGD step of CE(log_softmax(logits), target) on a layer y = x W + b
changes W by -lr * outer(x, dL/dy). Instead of a full copy of W per episode, each
episode keeps those vectors, one slot per update, and a forward pass adds their term to
the shared (trained) layer:

    x (W + sum_k u_k v_k^T) = x W + sum_k (x . u_k) v_k      u_k = x_k, v_k = -lr g_k

The LSTM is the only place where this pays: its input kernel (49 fuse channels x 4H)
and its recurrent kernel (H x 4H) are the bulk of the parameters (6.4 M + 1 M of 7.6 M
at the paper's widths). Both feed the same gate pre-activations, so one step's gate gradient g
is the v of both kernels and a slot stores (x_k, h_k, v_k):

    gates += ((U_x x + U_h h) * valid) @ V          U_x (K, in), U_h (K, H), V (K, 4H)

Every other parameter of the scope is a dense per-episode copy (vmapped, updated by
plain SGD): biases, the ORG adjacency, and every nn.Dense kernel. A Dense layer applied
at P positions (the 1x1 layers at 7x7, the per-category encoder layers at 22) would need
P (in + out) floats per update, so its copy is the cheaper form at our widths (e.g. the
global 1x1, 512 x 64: 33 k floats as a copy, 1.4 M for 50 updates at 49 positions);
narrow heads (actor 512 x 6, action 6 x 10) are smaller than one slot. The critic's
layers (POLICY_FREE) do not reach the policy logits (zero gradient) and stay shared.
`Plan` records the split, `plan_floats` the per-episode size: at the paper's widths
70 k floats of copies + 50 slots x 5.7 k = 355 k floats (1.4 MB) per episode, against
7.6 M floats (30 MB) for a full copy.

The slots are a fixed-size buffer per episode (`slots` = the updates between two resets:
TPNConfig.reset_every, or the longest episode); `count` says how many are in use, so a
reset (episode start, or every reset_every steps) only sets count to 0 and copies the
trained dense leaves back: stale slots are masked, never read. A step's update is kept
apart (`newest`) and written into its slot at the start of the next step, so that the
buffers are written once per step before any read and XLA updates them in place. The
slots are stored in blocks of SLOT_BLOCK, and only the blocks below the batch's largest
count are read (`lowrank_gates`: one lax.cond per block, a custom_vjp for the backward):
episodes of an evaluation batch start and reset together, so early in each reset window
few blocks are in use.

The forward pass reuses the flax modules: `nn.intercept_methods` adds the low-rank term
to LSTMGates.recur (the input kernel's part is computed in LSTMGates.project, where x is
seen) and, while a step is differentiated, a zero perturbation on the gates whose
gradient is g, and records x and h. A step runs the model three times over the batch:
forward (jax.vjp), backward (the dense copies' gradients and g), and again with the
updated weights (the action and the LSTM state come from those).

The gradient is truncated to the current step: the LSTM carry from the previous step is
a constant (the authors' release backpropagates through the retained graph of its
current 50-step chunk instead). The dense reference (fast_weights.py) makes the same
truncation, and tests check that both give the same weights and logits.

    plan = make_plan(base_variables, "all", slots=50)
    fw = LowRankFastWeights(model, plan)
    state = fw.init(B, base)                     # LowRankState, leading axis B
    logits, lstm, state, aux = fw.step(base, state, inputs, carry, decide, lr)
    weights = fw.materialize(base, state)        # dense per-episode weights (tests)
"""

from __future__ import annotations

import dataclasses
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import struct, traverse_util

from orgnav_jax.models.trunk import LSTMGates
from orgnav_jax.tpn.fast_weights import (
    PLACEMENTS, SCOPE_PATHS, _one, _unbatch, policy_ce_grad)
from orgnav_jax.tree import tile, where_rows

SLOT_BLOCK = 10     # slots read per loop iteration: only blocks below the batch's max count
# modules whose parameters never reach the policy logits (kept shared: zero gradient)
POLICY_FREE = (("params", "trunk", "critic_hidden"), ("params", "trunk", "critic"))


@dataclasses.dataclass(frozen=True)
class Site:
    """An LSTM layer whose kernels are low-rank: module path, input width, hidden H."""
    module: tuple[str, ...]
    din: int
    hidden: int

    @property
    def key(self) -> str:
        return "/".join(self.module)

    @property
    def slot_floats(self) -> int:
        return self.din + self.hidden + 4 * self.hidden

    def kernel(self, name: str) -> tuple[str, ...]:
        return ("params",) + self.module + (name,)


@dataclasses.dataclass(frozen=True)
class Plan:
    """Which parameters an episode holds, and how: `dense` flat paths (per-episode
    copies) and low-rank `sites` with `slots` update slots each."""
    scope: str
    slots: int
    dense: tuple[tuple[str, ...], ...]
    sites: tuple[Site, ...]

    @property
    def buffer_slots(self) -> int:
        """slots rounded up to whole blocks of SLOT_BLOCK."""
        return -(-self.slots // SLOT_BLOCK) * SLOT_BLOCK


def _prefixed(path, prefixes) -> bool:
    return any(path[:len(p)] == p for p in prefixes)


def make_plan(variables, scope: str, slots: int, lowrank: str = "cost") -> Plan:
    """The split of `scope`'s parameters (see module docstring). lowrank="cost": an LSTM
    layer is low-rank when `slots` slots are smaller than its two kernels; "always" /
    "never" force it (tests)."""
    if scope not in SCOPE_PATHS:
        raise ValueError(f"unknown test-time update scope {scope!r}: expected one of "
                         f"{sorted(SCOPE_PATHS)}")
    if slots < 1:
        raise ValueError(f"low-rank fast weights need >= 1 slot, got {slots}")
    flat = traverse_util.flatten_dict(variables)
    scoped = [k for k in flat if _prefixed(k, (SCOPE_PATHS[scope],))
              and not _prefixed(k, POLICY_FREE)]
    if not scoped:
        raise ValueError(f"scope {scope!r}: the model has no parameters under "
                         f"{SCOPE_PATHS[scope]}")
    sites = []
    for k in scoped:
        if k[-1] != "input_kernel" or k[:-1] + ("recurrent_kernel",) not in flat:
            continue
        din, four_h = flat[k].shape
        site = Site(k[1:-1], din, four_h // 4)
        dense_size = (site.din + site.hidden) * four_h
        if lowrank == "always" or (lowrank == "cost" and slots * site.slot_floats < dense_size):
            sites.append(site)
    low = {s.kernel(n) for s in sites for n in ("input_kernel", "recurrent_kernel")}
    return Plan(scope, slots, tuple(k for k in scoped if k not in low), tuple(sites))


def plan_floats(variables, plan: Plan) -> tuple[int, int]:
    """Floats one episode's fast weights hold: (dense copies, all slots)."""
    flat = traverse_util.flatten_dict(variables)
    return (sum(int(flat[k].size) for k in plan.dense),
            plan.buffer_slots * sum(s.slot_floats for s in plan.sites))


@struct.dataclass
class LowRankState:
    """One batch of episodes' fast weights (leading axis B everywhere): dense {path:
    (B, ...)}; factors {site key: {"x", "h", "v"}}, each a tuple of K / SLOT_BLOCK blocks
    (B, SLOT_BLOCK, in | H | 4H), slot k in block k // SLOT_BLOCK; count (B,) int32 slots
    in use; newest {site key: {"x", "h", "v"}} (B, ...) the last step's update, written
    into its slot at the start of the next step when newest_on (B,) (a write-behind: see
    LowRankFastWeights.step). pending: placement "release" only, the dense leaves after
    the newest update, applied with it when the next step commits (None otherwise)."""
    dense: Any
    factors: Any
    count: jax.Array
    newest: Any
    newest_on: jax.Array
    pending: Any = None


def _in_blocks(valid):
    return tuple(valid[i * SLOT_BLOCK:(i + 1) * SLOT_BLOCK]
                 for i in range(valid.shape[0] // SLOT_BLOCK))


def _sum_blocks(term, blocks, n, like):
    """sum of term(i) over the blocks i < `blocks` (of n); a lax.cond per block, so the
    blocks past the batch's last used slot are not read."""
    out = jnp.zeros_like(like)
    for i in range(n):
        out = out + jax.lax.cond(i < blocks, lambda i=i: term(i), lambda: jnp.zeros_like(like))
    return out


@jax.custom_vjp
def lowrank_gates(x, h, ux, uh, v, valid, blocks):
    """One environment's low-rank gate term sum_i ((ux_i x + uh_i h) * valid_i) @ v_i over
    the first `blocks` blocks (the later ones are empty in every row of the batch and are
    not read): x (in,), h (H,); ux, uh, v tuples of blocks (S, in), (S, H), (S, 4H);
    valid (K,) float; blocks () int32 -> (4H,). Whole arrays per block: XLA's CPU dots
    read slices of a larger buffer far slower. The gradient reaches x only: h is the
    carry from the previous step (a constant: the truncated gradient) and the slots are
    data."""
    valid = _in_blocks(valid)
    return _sum_blocks(lambda i: ((ux[i] @ x + uh[i] @ h) * valid[i]) @ v[i], blocks, len(v),
                       v[0][0])


def _lowrank_fwd(x, h, ux, uh, v, valid, blocks):
    return lowrank_gates(x, h, ux, uh, v, valid, blocks), (ux, v, valid, blocks)


def _lowrank_bwd(res, ct):
    ux, v, valid, blocks = res
    valid = _in_blocks(valid)
    dx = _sum_blocks(lambda i: ((v[i] @ ct) * valid[i]) @ ux[i], blocks, len(v), ux[0][0])
    return dx, None, None, None, None, None, None


lowrank_gates.defvjp(_lowrank_fwd, _lowrank_bwd)


def _interceptor(plan: Plan, factors, count, blocks, newest, perts, seen: dict):
    """A flax method interceptor adding the sites' low-rank terms (one environment, the
    model's batch axis of 1): slots < count of `factors` (in the first `blocks` blocks),
    plus `newest` = (vectors, on) if given. With `perts` it adds those to the gates too
    and records the layers' inputs in seen[key] = {"x", "h"}."""
    sites = {s.module: s for s in plan.sites}
    pending = {}

    def intercept(next_fun, args, kwargs, context):
        module = context.module
        site = sites.get(module.path) if isinstance(module, LSTMGates) else None
        if site is None or context.method_name not in ("project", "recur"):
            return next_fun(*args, **kwargs)
        f = factors[site.key]
        if context.method_name == "project":           # x (1, in): the input kernel's input
            pending[site.key] = args[0]
            if perts is not None:
                seen.setdefault(site.key, {})["x"] = args[0][0]
            return next_fun(*args, **kwargs)
        gates, carry = args[:2]                        # recur: gates (1, 4H), carry (c, h)
        h = carry[1]
        if site.key not in pending:
            raise RuntimeError(f"low-rank fast weights: {site.key}.recur without its project "
                               "in the same step")
        x = pending.pop(site.key)
        valid = (jnp.arange(plan.buffer_slots) < count).astype(gates.dtype)
        gates = gates + lowrank_gates(x[0], h[0], f["x"], f["h"], f["v"], valid, blocks)
        if newest is not None:
            n, on = newest[0][site.key], newest[1]
            gates = gates + (on * (x @ n["x"] + h @ n["h"]))[:, None] * n["v"]
        if perts is not None:
            gates = gates + perts[site.key][None]
            seen.setdefault(site.key, {})["h"] = h[0]
        return next_fun(gates, carry, *args[2:], **kwargs)

    return intercept, pending


class LowRankFastWeights:
    """Per-episode fast weights of `plan` for a NavModel (see module docstring)."""

    def __init__(self, model, plan: Plan, placement: str = "state"):
        if placement not in PLACEMENTS:
            raise ValueError(f"TPN placement {placement!r}: expected one of {PLACEMENTS}")
        self.model, self.plan, self.placement = model, plan, placement
        self._v_apply = jax.vmap(self._apply_row, in_axes=(None, 0, 0, 0, None, 0, 0, 0, 0))

    def __hash__(self):
        return hash((self.model, self.plan, self.placement))

    def __eq__(self, other):
        return isinstance(other, LowRankFastWeights) and (
            self.model, self.plan, self.placement) == (other.model, other.plan,
                                                       other.placement)

    def _split(self, base):
        flat = traverse_util.flatten_dict(base)
        return {k: v for k, v in flat.items() if k not in set(self.plan.dense)}, \
            {k: flat[k] for k in self.plan.dense}

    def init(self, batch: int, base) -> LowRankState:
        _, dense = self._split(base)
        z = lambda *shape: jnp.zeros((batch,) + shape)
        blocks = range(self.plan.buffer_slots // SLOT_BLOCK)
        factors = {s.key: {n: tuple(z(SLOT_BLOCK, d) for _ in blocks) for n, d in
                           (("x", s.din), ("h", s.hidden), ("v", 4 * s.hidden))}
                   for s in self.plan.sites}
        newest = {s.key: {"x": z(s.din), "h": z(s.hidden), "v": z(4 * s.hidden)}
                  for s in self.plan.sites}
        dense = tile(dense, batch)
        return LowRankState(dense, factors, jnp.zeros(batch, jnp.int32), newest,
                            jnp.zeros(batch, bool),
                            dense if self.placement == "release" else None)

    def reset(self, base, state: LowRankState, mask) -> LowRankState:
        """mask (B,) bool: those rows go back to the trained weights."""
        _, dense = self._split(base)
        dense = jax.lax.cond(jnp.any(mask),     # most steps reset no row: skip the copy
                             lambda d: where_rows(mask, tile(dense, mask.shape[0]), d),
                             lambda d: d, state.dense)
        return state.replace(dense=dense, count=jnp.where(mask, 0, state.count),
                             newest_on=state.newest_on & ~mask)

    def _commit(self, state: LowRankState) -> LowRankState:
        """Write the newest update into slot `count` of its rows (in place: the buffers
        are not read before this in a step)."""
        rows = jnp.arange(state.count.shape[0])
        slot = jnp.where(state.newest_on, state.count, self.plan.buffer_slots)   # dropped

        def put(blocks, x):             # rows whose slot is not in block i write nowhere
            at = [slot - i * SLOT_BLOCK for i in range(len(blocks))]
            return tuple(buf.at[rows, jnp.where(j >= 0, j, SLOT_BLOCK)].set(x, mode="drop")
                         for buf, j in zip(blocks, at))
        factors = {k: {n: put(f[n], state.newest[k][n]) for n in f}
                   for k, f in state.factors.items()}
        return state.replace(factors=factors, count=state.count + state.newest_on,
                             newest_on=jnp.zeros_like(state.newest_on))

    def _apply_row(self, shared, dense, factors, count, blocks, newest, inputs, carry, perts):
        """One environment (no batch axis) -> (logits (6,), (carry, h (H,), seen))."""
        seen: dict = {}
        intercept, pending = _interceptor(self.plan, factors, count, blocks, newest, perts,
                                          seen)
        variables = traverse_util.unflatten_dict({**shared, **dense})
        with nn.intercept_methods(intercept):
            logits, _, carry, h = self.model.apply(variables, _one(inputs), _one(carry))
        if pending or (perts is not None and set(seen) != set(perts)):
            raise RuntimeError("low-rank fast weights: the model did not run every LSTM "
                               f"site once (pending {sorted(pending)}, seen {sorted(seen)})")
        return logits[0], (_unbatch(carry), h[0], seen)

    def step(self, base, state: LowRankState, inputs, carry, decide, lr, commit=None):
        """One test-time step for a batch: forward with the episodes' fast weights;
        decide(logits (B, 6), h (B, H)) -> (target (B,), update (B,) bool, aux); rows with
        `update` take one SGD step of CE(logits, target) and act with the new weights.
        -> (logits (B, 6), carry, state, aux).

        The previous step's update is written into its slot first; this step's update is
        kept apart in state.newest (the re-run adds its term explicitly) and written at the
        next step. So every step reads the slot buffers only after its single write, and
        XLA updates them in place (writing them after the reads made it copy all of them
        twice per step, the largest cost at 50 slots).

        placement "release": the previous step's update is written (and its dense leaves
        applied) only for rows whose `commit` (B,) is set; this step's update is computed
        on this step's logits and kept pending, and the step is not re-run."""
        shared, _ = self._split(base)
        if self.placement == "release":
            on = state.newest_on & commit
            state = state.replace(dense=where_rows(on, state.pending, state.dense),
                                  newest_on=on)
        state = self._commit(state)
        B = state.count.shape[0]
        perts = {s.key: jnp.zeros((B, 4 * s.hidden)) for s in self.plan.sites}

        blocks = (jnp.max(state.count) + SLOT_BLOCK - 1) // SLOT_BLOCK   # same for all rows

        def forward(dense, perts):
            return self._v_apply(shared, dense, state.factors, state.count, blocks, None,
                                 inputs, carry, perts)

        logits, vjp_fn, (lstm, h, seen) = jax.vjp(forward, state.dense, perts, has_aux=True)
        target, update, aux = decide(logits, h)
        # rows that do not update get a zero cotangent, so a zero gradient: p - lr * 0 = p
        g_dense, g_gates = vjp_fn(policy_ce_grad(logits, target) * update[:, None])
        dense = jax.tree_util.tree_map(lambda p, g: p - lr * g, state.dense, g_dense)
        newest = {s.key: {"x": seen[s.key]["x"], "h": seen[s.key]["h"],
                          "v": -lr * g_gates[s.key]} for s in self.plan.sites}
        if self.placement == "release":          # pending until the next step commits it
            return logits, lstm, state.replace(newest=newest, newest_on=update,
                                               pending=dense), aux
        new = state.replace(dense=dense, newest=newest, newest_on=update)
        logits2, (lstm2, _, _) = self._v_apply(shared, dense, state.factors, state.count,
                                               blocks, (newest, update.astype(jnp.float32)),
                                               inputs, carry, None)
        logits, lstm = where_rows(update, (logits2, lstm2), (logits, lstm))
        return logits, lstm, new, aux

    def materialize(self, base, state: LowRankState):
        """-> {path: (B, ...)} the scope's weights each episode acts with (dense copies,
        trained + low-rank kernels), as fast_weights.split_scope lays them out (tests);
        placement "release": before the pending update."""
        if self.placement == "release":
            state = state.replace(newest_on=jnp.zeros_like(state.newest_on))
        state = self._commit(state)
        flat = traverse_util.flatten_dict(base)
        B = state.count.shape[0]
        out = dict(state.dense)
        valid = (jnp.arange(self.plan.buffer_slots)[None] < state.count[:, None]).astype(
            jnp.float32)
        for s in self.plan.sites:
            f = {n: jnp.concatenate(blocks, axis=1) for n, blocks in state.factors[s.key].items()}
            for name, u in (("input_kernel", f["x"]), ("recurrent_kernel", f["h"])):
                delta = jnp.einsum("bk,bki,bko->bio", valid, u, f["v"])
                out[s.kernel(name)] = flat[s.kernel(name)][None] + delta
        prefix = SCOPE_PATHS[self.plan.scope]
        for k, v in flat.items():          # policy-free leaves of the scope: never change
            if k[:len(prefix)] == prefix and k not in out:
                out[k] = jnp.broadcast_to(v, (B,) + v.shape)
        return out

