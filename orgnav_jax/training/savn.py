"""SAVN (Wortsman et al., CVPR 2019): self-adaptive navigation by a learned loss, MAML.

Training (a stage-1 mode, `TrainConfig.savn`; presets `savn` (WE target) and `dsavn`
(detections); docs/savn.md): every update steps `num_envs` batch rows for `savn_segments`
segments of k = `savn_steps` steps; a row whose episode ended starts a new one at the next
segment boundary (savn_loss). After each of the first `savn_inner_steps` segments that did
not end its episode, the episode's fast weights take one SGD step (`savn_inner_lr`) on the
learned interaction loss of that segment (`LearnedLoss`: a temporal convolution over the
segment's LSTM outputs and action distributions, its output's L2 norm), and act with them
for the rest of the episode. The A2C loss of the episodes is taken with the weights in
force at each step, and its gradient (`jax.grad` through the inner steps, second order
unless `savn_first_order`) trains the initial parameters and the learned loss. At test
time (`savn_policy`) the same inner steps run with the learned loss only.

Fast weights (`Fast`, per batch row): every parameter of the navigation network. Every
LSTM layer's input and recurrent kernels (most of the parameters) stay shared and each
row keeps its updates as low-rank factors: one segment's SGD step on a layer's kernels is
-lr sum_t x_t^T d_t (x_t the layer's input, d_t its gate gradient at step t), so a slot
holds (x_t, h_{t-1}, -lr d_t) and the forward pass adds sum_j (x . ux_j + h . uh_j) v_j
to the layer's gates (the idea of tpn/lowrank.py, written plainly here so that jax
differentiates through it a second time). All other parameters are dense per-row copies
(small). Slots not yet written are zero and add nothing, so shapes are fixed:
savn_inner_steps x k slots per layer.

    meta = init_meta(model, learned, cfg, scenes, key)       # {"nav": ..., "ll": ...}
    loss, (aux, stats, rows) = savn_loss(meta, rows, model, learned, cfg, scenes, key)
    chunk = make_savn_chunk(cfg, model, learned, optimizer)  # jitted
    policy = savn_policy(model, learned, k, inner_steps, inner_lr)
"""

from __future__ import annotations

from functools import partial
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax
from flax import struct, traverse_util

from orgnav_jax import env
from orgnav_jax.compile_cache import compiled_once
from orgnav_jax.constants import FEATURE_GRID, NUM_ACTIONS
from orgnav_jax.errors import choose
from orgnav_jax.evaluation import Policy
from orgnav_jax.models import init_params, model_inputs, previous_action, reset_carry
from orgnav_jax.models.navmodel import ModelInputs
from orgnav_jax.training.losses import gae
from orgnav_jax.training.rollout import EpisodeStats
from orgnav_jax.tree import tile, where_rows

# The config version from which a SAVN update refills ended rows at segment boundaries
# and its runner (SavnRunner.rows) carries the running episodes to the next update (issue
# 40); before, an update stepped num_envs whole episodes to the cap (runner rows None).
REFILL_VERSION = 8
# The config version from which the rows' fast weights keep every LSTM layer's kernels as
# low-rank slots (Fast: a tuple per layer); in version 8 only the first layer's were, the
# others' updates were dense per-row copies (legacy_rows converts to that layout).
LAYERED_VERSION = 9

KERNELS = {"input_kernel": "ux", "recurrent_kernel": "uh"}   # low-rank, per LSTM layer
VALUE_HEAD = ("critic_hidden", "critic")    # the trunk's modules the learned loss does not
                                            # reach: shared by the rows (split_params)


def lstm_module(i: int) -> tuple[str, str]:
    """The module path of the trunk's LSTM layer i."""
    return ("trunk", f"lstm_{i}")


def kernel_path(i: int, name: str) -> tuple[str, ...]:
    return ("params",) + lstm_module(i) + (name,)


class LearnedLoss(nn.Module):
    """The release's learned loss: H (k, F) (F = LSTM width + 6 action probabilities) is
    read as k channels over F positions; two causal convolutions of kernel 2 (dilations 1
    and 2; 10 then 1 channels, leaky ReLU after each), written as Dense over the shifted
    inputs; the loss is the L2 norm of the output (the release's pow(2).sum().pow(0.5);
    a 1e-12 inside the root keeps its gradient finite at 0)."""
    channels: int = 10

    @nn.compact
    def __call__(self, H):
        x = H.T                                           # (F, k): positions x channels
        for i, width in enumerate((self.channels, 1)):
            d = 2 ** i
            shifted = jnp.pad(x, ((d, 0), (0, 0)))[:-d]   # x_{p - d}, zero before the start
            x = nn.leaky_relu(nn.Dense(width, name=f"conv{i}_now")(x)
                              + nn.Dense(width, use_bias=False, name=f"conv{i}_past")(shifted))
        return jnp.sqrt(jnp.sum(x ** 2) + 1e-12)


@struct.dataclass
class Fast:
    """Per-row fast weights (leading axis B): dense copies of every parameter but the
    LSTM layers' kernels, and those kernels' low-rank updates (R slots), a tuple entry
    per LSTM layer l."""
    dense: Any            # flat {path: (B, ...)}
    ux: tuple             # (B, R, in_l)  layer l's input at each slot's step
    uh: tuple             # (B, R, H)     layer l's state before that step
    v: tuple              # (B, R, 4H)    -lr x layer l's gate gradient there (0: unused)

    def zero_pert(self, steps: int) -> tuple:
        """Zero gate perturbations (B, steps, 4H) per layer (segment_rows' `pert`)."""
        return tuple(jnp.zeros((v.shape[0], steps, v.shape[-1]), v.dtype) for v in self.v)


@struct.dataclass
class SavnRows:
    """The episodes in the batch rows between updates (leading axis N; savn_loss). A row
    whose episode ended starts a new one at the next segment boundary; an episode still
    running at an update's end goes on in the next update from here, its fast weights
    kept as offsets over the meta-parameters they were made from (`offsets`: dense
    fast - meta; the low-rank slots are offsets already), constants for the next update."""
    env_state: env.EnvState
    lstm: Any              # the LSTM carry after the update's last step
    delta: Fast            # fast weights - meta-parameters
    updates: jax.Array     # (N,) int32 inner steps the running episode has taken
    ep_return: jax.Array   # (N,) float32 its return so far
    running: jax.Array     # (N,) bool: an episode is running (else one starts at the
                           #   next segment boundary)


@struct.dataclass
class SavnRunner:
    params: Any           # {"nav": navigation variables, "ll": learned-loss variables}
    opt_state: Any
    key: jax.Array
    update: jax.Array
    rows: SavnRows | None = None   # None: the form of runs of config version <= 7


def split_params(nav):
    """Navigation variables -> (shared: what every row uses as it is, dense: per-row
    copies, the rest), flat dicts {path: array}. Shared: every LSTM layer's input and
    recurrent kernels (each row's updates of them are its low-rank slots) and the value
    head (VALUE_HEAD): the learned loss reads the LSTM output and the action distribution,
    not the value, so the value head's inner gradient is zero and every row's copy would
    be the meta-parameters themselves (per-row copies before 2026-12-05)."""
    flat = traverse_util.flatten_dict(nav)
    if kernel_path(0, "input_kernel") not in flat:
        raise ValueError(f"SAVN: the model has no {'/'.join(kernel_path(0, 'input_kernel'))}")
    low = {kernel_path(i, n) for i in range(num_layers(flat)) for n in KERNELS}
    low |= value_head(flat)
    return ({p: flat[p] for p in low}, {p: x for p, x in flat.items() if p not in low})


def value_head(flat) -> set:
    """The value head's paths in a flat parameter dict (the trunk's VALUE_HEAD modules)."""
    return {p for p in flat if len(p) >= 4 and p[1] == "trunk" and p[2] in VALUE_HEAD}


def num_layers(flat_or_shared) -> int:
    """LSTM layers of the trunk in a flat parameter dict."""
    i = 0
    while kernel_path(i, "input_kernel") in flat_or_shared:
        i += 1
    return i


def merge_params(shared, dense):
    return traverse_util.unflatten_dict({**shared, **dense})


def init_fast(nav, batch: int, slots: int) -> Fast:
    """Every row's fast weights = the trained parameters (no slot written)."""
    shared, dense = split_params(nav)
    layers = range(num_layers(shared))
    w_in = [shared[kernel_path(i, "input_kernel")] for i in layers]
    w_h = [shared[kernel_path(i, "recurrent_kernel")] for i in layers]
    z = lambda n, w: jnp.zeros((batch, slots, n), w.dtype)
    return Fast(tile(dense, batch), tuple(z(w.shape[0], w) for w in w_in),
                tuple(z(w.shape[0], w) for w in w_h), tuple(z(w.shape[1], w) for w in w_in))


def reset_fast(nav, fast: Fast, mask) -> Fast:
    """Rows where mask (B,) go back to the trained parameters."""
    return where_rows(mask, init_fast(nav, mask.shape[0], fast.v[0].shape[1]), fast)


def materialize(nav, fast: Fast):
    """-> per-row navigation variables (B, ...) with the low-rank updates added (tests)."""
    shared, _ = split_params(nav)
    B = fast.v[0].shape[0]
    full = {**fast.dense, **tile(shared, B)}
    for i, v in enumerate(fast.v):
        for name, u in KERNELS.items():
            full[kernel_path(i, name)] = shared[kernel_path(i, name)][None] + jnp.einsum(
                "bri,bro->bio", getattr(fast, u)[i], v)
    return traverse_util.unflatten_dict(full)


def _one(tree):
    return jax.tree_util.tree_map(lambda x: x[None], tree)


def _unbatch(tree):
    return jax.tree_util.tree_map(lambda x: x[0], tree)


def _coef(u, x):
    """x's coefficients on the slots, x . u_j: u (R, n), x (n,) or (L, n) -> (R,) or
    (L, R). The low-rank term of a layer is (x . ux_j + h . uh_j) summed against v_j
    (_lowrank): one product with v per step for both kernels. Written u @ x^T, not
    x @ u^T: the gradient for u then comes out in u's own layout (R, n); x @ u^T's came
    as (n, R) and was transposed (in the compiled update, the (64, 24, 784) transposes
    and copies went from 14 to 8, docs/history/savn-speed.md)."""
    return u @ x if x.ndim == 1 else (u @ x.T).T


def _lowrank(coef, v):
    """sum_j coef_j v_j: coef (..., R), v (R, 4H) -> (..., 4H). A product (under vmap, a
    batched matrix-vector product); a multiply-reduce over the slots ran at about
    1 GFLOP/s on CPU (docs/history/savn-speed.md)."""
    return coef @ v


def embed_row(model, shared, dense, ux0, inputs):
    """One row's non-recurrent part over L steps: inputs (ModelInputs, leading L) ->
    (the first LSTM layer's input gates (L, 4H) from the shared kernel, that layer's
    input x (L, in_0), x's coefficients on the layer's input slots (L, R); step_row adds
    the low-rank term)."""
    seen = {}

    def hook(next_fun, args, kwargs, context):
        if context.method_name == "project" and tuple(context.module.path) == lstm_module(0):
            seen["x"] = args[0]
        return next_fun(*args, **kwargs)

    with nn.intercept_methods(hook):
        gates = model.apply(merge_params(shared, dense), inputs, method=model.embed)
    return gates, seen["x"], _coef(ux0, seen["x"])


def step_row(model, shared, dense, ux, uh, v, carry, gates, coef0, pert):
    """One row, one step of the recurrence (no heads): gates (4H,) and coef0 (R,) from
    embed_row, pert (per layer (4H,)) -> (carry, each layer's state h after the step
    (per layer (H,))). Each layer's gates get its low-rank term (x . ux_j + h . uh_j) v_j
    (x its input, h its state before the step) and `pert`."""
    layer_of = {lstm_module(i): i for i in range(len(v))}
    x_of = {}

    def hook(next_fun, args, kwargs, context):
        i = layer_of.get(tuple(context.module.path))
        if i is not None and context.method_name == "project":     # layers >= 1
            x_of[i] = args[0]
            return next_fun(*args, **kwargs)
        if i is not None and context.method_name == "recur":
            gates_i, (c_i, h_i) = args
            coef = (coef0 if i == 0 else _coef(ux[i], x_of[i])) + _coef(uh[i], h_i)
            return next_fun(gates_i + _lowrank(coef, v[i]) + pert[i], (c_i, h_i))
        return next_fun(*args, **kwargs)

    with nn.intercept_methods(hook):
        c, _ = model.apply(merge_params(shared, dense), gates, carry, method=model.lstm_step)
    return c, tuple(h for _, h in c.lstm)


def segment_rows(model, shared, dense, ux, uh, v, carry, inputs, pert):
    """B rows (episodes) for L steps with their fast weights: dense, ux, uh, v (leading
    B); carry: NavCarry (per LSTM layer (c, h), each (B, H); the previous step's action
    probabilities (B, 6)); inputs: ModelInputs (B, L, ...); pert (per layer (B, L, 4H))
    added to each LSTM layer's gates (its gradient is the gate gradient) -> (logits
    (B, L, 6), values (B, L), h (B, L, H), carry (holding the last step's probabilities),
    x (per layer (B, L, in_l): the layer's inputs), h_prev (per layer (B, L, H): its state
    before each step)). The non-recurrent part runs once over the L steps (embed_row); the
    recurrence is a scan over time whose step runs every row (step_row under vmap): the
    shared kernels are products over the batch, each row's updates the low-rank terms
    added to its gates. The scan yields each layer's states only (the inputs of layers
    >= 1 and the states before each step are those, shifted); the heads run once over the
    L steps after it."""
    gates, x0, coef0 = jax.vmap(embed_row, in_axes=(None, None, 0, 0, 0))(
        model, shared, dense, ux[0], inputs)
    rows_step = jax.vmap(step_row, in_axes=(None, None, 0, 0, 0, 0, 0, 0, 0, 0))
    time_major = lambda t: jax.tree_util.tree_map(lambda y: jnp.swapaxes(y, 0, 1), t)

    def body(c, xs):
        return rows_step(model, shared, dense, ux, uh, v, c, *xs)

    h0 = tuple(h for _, h in carry.lstm)
    if gates.shape[1] == 1:                           # one step (acting): no loop
        carry, hs = body(carry, (gates[:, 0], coef0[:, 0], tuple(q[:, 0] for q in pert)))
        hs = tuple(h[:, None] for h in hs)
    else:
        carry, hs = jax.lax.scan(body, carry, time_major((gates, coef0, pert)))
        hs = time_major(hs)
    h_prev = tuple(jnp.concatenate([a[:, None], h[:, :-1]], axis=1) for a, h in zip(h0, hs))
    # the heads are outside the recurrence: once over the L steps, not in the scan
    heads = lambda d, hh: model.apply(merge_params(shared, d), hh, method=model.actor_critic)
    logits, values = jax.vmap(heads)(dense, hs[-1])
    return (logits, values, hs[-1], model.with_probs(carry, logits[:, -1]), (x0,) + hs[:-1],
            h_prev)


def segment_row(model, shared, dense, ux, uh, v, carry, inputs, pert):
    """segment_rows for one row (no leading B anywhere)."""
    out = segment_rows(model, shared, *_one((dense, ux, uh, v, carry, inputs, pert)))
    return _unbatch(out)


def learned_input(logits, h):
    """The learned loss's input: [LSTM output, action distribution] per step (L, H + 6)."""
    return jnp.concatenate([h, jax.nn.softmax(logits)], axis=-1)


def inner_rows(model, learned, shared, dense, ux, uh, v, carry, inputs, ll_params, lr,
               slot, on, first_order: bool = False):
    """B rows: the segment's forward pass (segment_rows) and one SGD step (lr; only where
    `on` (B,)) of each row's learned loss on its fast weights, whose updates of the LSTM
    layers' kernels go into slots slot .. slot + L - 1 (slot (B,)) -> (logits, values,
    carry, learned loss (B,), new dense, ux, uh, v); where not `on` the fast weights come
    back unchanged. first_order: the step's gradient is a constant for outer gradients."""
    B, L = jax.tree_util.tree_leaves(inputs)[0].shape[:2]

    def loss_of(dense, pert):            # rows are independent: the sum's gradient is
        logits, values, h, carry_out, x, h_prev = segment_rows(   # each row's own
            model, shared, dense, ux, uh, v, carry, inputs, pert)
        ll = jax.vmap(lambda lg, hh: learned.apply(ll_params, learned_input(lg, hh)))(
            logits, h)
        return ll.sum(), (ll, logits, values, carry_out, x, h_prev)

    (_, (ll, logits, values, carry_out, x, h_prev)), (g_dense, delta) = jax.value_and_grad(
        loss_of, argnums=(0, 1), has_aux=True)(dense, tuple(
            jnp.zeros((B, L, w.shape[-1]), w.dtype) for w in v))
    sg = jax.lax.stop_gradient if first_order else (lambda t: t)
    step = lr * on.astype(v[0].dtype)

    def put(buf, new, slot, on):   # slots slot .. slot + L - 1, unchanged where not `on`
        old = jax.lax.dynamic_slice_in_dim(buf, slot, L, 0)
        return jax.lax.dynamic_update_slice_in_dim(buf, jnp.where(on, new, old), slot, 0)

    put_rows = lambda bufs, news: tuple(jax.vmap(put)(b, sg(n), slot, on)
                                        for b, n in zip(bufs, news))
    dense = jax.tree_util.tree_map(
        lambda p, g: p - step.reshape((B,) + (1,) * (p.ndim - 1)) * sg(g), dense, g_dense)
    return (logits, values, carry_out, ll, dense, put_rows(ux, x), put_rows(uh, h_prev),
            put_rows(v, tuple(-lr * d for d in delta)))


def inner_row(model, learned, shared, dense, ux, uh, v, carry, inputs, ll_params, lr,
              slot: int | jax.Array, on, first_order: bool = False):
    """inner_rows for one row (no leading B; slot and on scalars)."""
    batched = _one((dense, ux, uh, v, carry, inputs)) + (ll_params, lr) + _one(
        (jnp.asarray(slot), jnp.asarray(on)))
    return _unbatch(inner_rows(model, learned, shared, *batched, first_order=first_order))


def build_learned_loss() -> LearnedLoss:
    return LearnedLoss()


def init_meta(model, learned: LearnedLoss, cfg, scenes, key):
    """{"nav": navigation variables, "ll": learned-loss variables}."""
    k_nav, k_ll = jax.random.split(key)
    nav = init_params(model, k_nav, scenes)
    return {"nav": nav, "ll": learned.init(k_ll, jnp.zeros((cfg.savn_steps,
                                                             cfg.hidden + 6)))}


def fast_over(nav, delta: Fast) -> Fast:
    """Rows' fast weights from their offsets over the meta-parameters `nav` (SavnRows'
    `delta`): dense nav + delta.dense, the low-rank slots as they are (they are offsets
    already). delta.dense also holds the value head's offsets, always zero (see offsets);
    they are dropped."""
    _, dense = split_params(nav)
    return delta.replace(dense={p: x[None] + delta.dense[p] for p, x in dense.items()})


def offsets(nav, fast: Fast) -> Fast:
    """The inverse of fast_over: the rows' fast weights as offsets over `nav`, with the
    value head's (zero: split_params) added, so that the rows' checkpoints keep the layout
    of config version 9 (every parameter but the LSTM kernels per row)."""
    shared, dense = split_params(nav)
    B = fast.v[0].shape[0]
    zeros = {p: jnp.zeros((B,) + shared[p].shape, shared[p].dtype)
             for p in value_head(shared)}
    return fast.replace(dense={**zeros, **{p: f - dense[p][None]
                                           for p, f in fast.dense.items()}})


def init_rows(cfg, model, nav, scenes, key) -> SavnRows:
    """num_envs rows with no episode running: each starts one at the first segment."""
    N = cfg.num_envs
    _, state = jax.vmap(env.reset, in_axes=(0, None, None))(
        jax.random.split(key, N), scenes, train_env_params(cfg))
    return SavnRows(state, model.initial_carry(N),
                    offsets(nav, init_fast(nav, N, cfg.savn_inner_steps * cfg.savn_steps)),
                    jnp.zeros(N, jnp.int32), jnp.zeros(N, jnp.float32), jnp.zeros(N, bool))


def train_env_params(cfg) -> env.EnvParams:
    cap = cfg.episode_cap
    return env.EnvParams(success_reward=cfg.success_reward, step_penalty=cfg.step_penalty,
                         step_caps=(cap,) * 4)


def unrolled(body, carry, xs):
    """jax.lax.scan(body, carry, xs) written out (a Python loop): under the second-order
    gradient XLA keeps each segment's residuals as they are instead of stacking them into
    loop buffers: 1.15-1.4x the scan's speed, a 3-5x longer compile
    (docs/history/savn-speed.md)."""
    outs = []
    for i in range(xs.shape[0]):
        carry, y = body(carry, xs[i])
        outs.append(y)
    return carry, jax.tree_util.tree_map(lambda *a: jnp.stack(a), *outs)


def savn_loss(meta, rows: SavnRows, model, learned, cfg, scenes, key, trace: bool = False):
    """The meta-objective of one update: every row stepped for savn_segments segments of
    k steps, episodes refilled at segment boundaries -> (A2C loss over the valid steps,
    (aux, EpisodeStats sums of the episodes that ended, the rows for the next update)).

    At each segment's start a row whose episode ended starts a new one: a fresh env
    episode, a zero LSTM carry and fast weights = the meta-parameters (the new episode's
    own place in the meta-gradient), no inner step taken. The row acts k steps with its
    weights (an episode that ends inside the segment leaves the row idle, masked, to the
    boundary); then, if its episode is still running and has taken fewer than
    savn_inner_steps inner steps, its fast weights take one SGD step on the segment's
    learned loss. An episode still running at the update's end is cut there: its value
    at the next state bootstraps the advantages (as A2C's rollouts), and it goes on in
    the next update from the returned rows, its fast weights kept as constant offsets
    over the meta-parameters (stop_gradient: the meta-gradient of its later steps does
    not reach back through the inner steps taken before the cut).
    trace: aux["trace"] holds per-segment arrays (leading axis savn_segments) for tests:
    after the refill, which rows started an episode ("new"), their inner steps taken
    ("updates"), fast weights ("fast") and LSTM carry ("lstm"); the segment's inputs
    (N, k, ...), logits (k, N, 6) and valid steps (k, N)."""
    N, k, U = cfg.num_envs, cfg.savn_steps, cfg.savn_segments
    params_env = train_env_params(cfg)
    nav = meta["nav"]
    shared, meta_dense = split_params(nav)
    fresh_dense = tile(meta_dense, N)
    v_reset = jax.vmap(env.reset, in_axes=(0, None, None))
    v_step = jax.vmap(env.step_env, in_axes=(0, 0, None, None))
    v_observe = jax.vmap(env.observe, in_axes=(0, None))
    v_segment = partial(segment_rows, model)
    v_inner = partial(inner_rows, model, learned, first_order=cfg.savn_first_order)
    sg = jax.lax.stop_gradient
    sh_sg = sg(shared)

    def observe(state, lstm):
        inputs = model_inputs(scenes, v_observe(state, scenes))
        return inputs._replace(prev_action=previous_action(model, inputs.prev_action, lstm))

    def segment(c, key):
        state, lstm, fast, updates, running, ep_return, stats, ll_sum = c
        k_reset, k_act = jax.random.split(key)
        # rows whose episode ended start a new one: the meta-parameters, a zero carry
        new = ~running
        _, fresh_state = v_reset(jax.random.split(k_reset, N), scenes, params_env)
        state = where_rows(new, fresh_state, state)
        lstm = reset_carry(lstm, new)
        # (a slot whose v is zero adds nothing: ux, uh of the last episode may stay)
        fast = Fast(where_rows(new, fresh_dense, fast.dense), fast.ux, fast.uh,
                    tuple(v * (~new).astype(v.dtype)[:, None, None] for v in fast.v))
        updates = jnp.where(new, 0, updates)
        ep_return = jnp.where(new, 0.0, ep_return)
        f_sg, lstm_in = sg(fast), lstm

        def act(c, key):        # the agent acts with this segment's weights (no gradient)
            state, lstm, running, ep_return, stats = c
            inputs = observe(state, lstm)
            logits, _, _, lstm, _, _ = v_segment(
                sh_sg, f_sg.dense, f_sg.ux, f_sg.uh, f_sg.v, lstm,
                jax.tree_util.tree_map(lambda x: x[:, None], inputs), f_sg.zero_pert(1))
            action = jax.random.categorical(key, logits[:, 0]).astype(jnp.int32)
            _, state2, reward, done, info = v_step(state, action, scenes, params_env)
            state = where_rows(running, state2, state)
            reward = jnp.where(running, reward, 0.0)
            ended = running & done
            ep_return = ep_return + reward
            spl = info["success"] * info["optimal_len"] / jnp.maximum(
                jnp.maximum(info["path_len"], info["optimal_len"]), 1)
            d = ended.astype(jnp.float32)
            stats = EpisodeStats(stats.count + d.sum(),
                                 stats.success + (d * info["success"]).sum(),
                                 stats.spl + (d * spl).sum(), stats.ret + (d * ep_return).sum(),
                                 stats.length + (d * info["steps"]).sum())
            out = (inputs, action, reward, ended | ~running, running)
            return (state, lstm, running & ~done, ep_return, stats), out

        (state, _, running, ep_return, stats), (inputs, action, reward, done, valid) = \
            jax.lax.scan(act, (state, sg(lstm), jnp.ones(N, bool), ep_return, stats),
                         jax.random.split(k_act, k))
        seg = jax.tree_util.tree_map(lambda x: jnp.swapaxes(x, 0, 1), inputs)   # (N, k, ..)
        # the differentiable pass over the segment, and the inner step where it is due
        on = running & (updates < cfg.savn_inner_steps)
        logits, values, lstm, ll, dense, ux, uh, v = v_inner(
            shared, fast.dense, fast.ux, fast.uh, fast.v, lstm, seg, meta["ll"],
            cfg.savn_inner_lr, jnp.minimum(updates, cfg.savn_inner_steps - 1) * k, on)
        fast = Fast(dense, ux, uh, v)
        out = (jnp.swapaxes(logits, 0, 1), jnp.swapaxes(values, 0, 1), action, reward, done,
               valid)
        if trace:
            out = out + ({"new": new, "inputs": seg, "updates": updates, "fast": f_sg,
                          "lstm": sg(lstm_in)},)
        updates = updates + on.astype(jnp.int32)
        return (state, lstm, fast, updates, running, ep_return, stats,
                ll_sum + jnp.stack([(ll * on).sum(), on.sum()])), out

    start = (rows.env_state, rows.lstm, fast_over(nav, rows.delta), rows.updates,
             rows.running, rows.ep_return, EpisodeStats.zeros(), jnp.zeros(2))
    (state, lstm, fast, updates, running, ep_return, stats, ll_sum), outs = unrolled(
        segment, start, jax.random.split(key, U))
    logits, values, action, reward, done, valid = (
        x.reshape((U * k,) + x.shape[2:]) for x in outs[:6])          # (T, N, ...)
    # the bootstrap value of the episodes cut at the update's end (their next state)
    lstm_sg = sg(lstm)
    f_sg = sg(fast)
    _, boot, *_ = v_segment(sh_sg, f_sg.dense, f_sg.ux, f_sg.uh, f_sg.v, lstm_sg,
                            jax.tree_util.tree_map(lambda x: x[:, None],
                                                   observe(state, lstm_sg)),
                            f_sg.zero_pert(1))
    last_value = jnp.where(running, boot[:, 0], 0.0)
    mask = valid.astype(jnp.float32)                 # (T, N)
    adv, ret = gae(reward, sg(values), done, last_value, cfg.gamma, cfg.gae_lambda)
    steps = jnp.maximum(mask.sum(), 1.0)
    logp_all = jax.nn.log_softmax(logits)
    logp = jnp.take_along_axis(logp_all, action[..., None], -1)[..., 0]
    policy_loss = -(sg(adv) * logp * mask).sum() / steps
    value_loss = 0.5 * (((ret - values) ** 2) * mask).sum() / steps
    entropy = (-(jnp.exp(logp_all) * logp_all).sum(-1) * mask).sum() / steps
    loss = policy_loss + cfg.value_coef * value_loss - cfg.entropy_coef * entropy
    if cfg.optim == "release":   # the release sums over steps: here per row of the update
        loss = loss * sg(steps) / N
    aux = {"policy_loss": policy_loss, "value_loss": value_loss, "entropy": entropy,
           "learned_loss": ll_sum[0] / jnp.maximum(ll_sum[1], 1.0),
           "env_steps_real": mask.sum()}
    if trace:
        aux["trace"] = dict(outs[6], logits=outs[0], valid=outs[5])
    rows = SavnRows(state, lstm_sg, sg(offsets(nav, fast)), updates, ep_return, running)
    return loss, (aux, stats, rows)


def legacy_rows(rows: SavnRows) -> SavnRows:
    """The rows in the layout of config version 8 (its checkpoints; runs.py restores a
    version-8 runner with jax.eval_shape of this): layer 0's slots as arrays, the other
    layers' kernel updates as dense per-row offsets (sum_j u_j^T v_j)."""
    d = rows.delta
    dense = dict(d.dense)
    for i in range(1, len(d.v)):
        for name, u in KERNELS.items():
            dense[kernel_path(i, name)] = jnp.einsum("bri,bro->bio", getattr(d, u)[i], d.v[i])
    return rows.replace(delta=Fast(dense, d.ux[0], d.uh[0], d.v[0]))


def init_savn_runner(cfg, model, learned, optimizer, scenes, key) -> SavnRunner:
    k_params, k_run = jax.random.split(key)
    params = init_meta(model, learned, cfg, scenes, k_params)
    k_run, k_rows = jax.random.split(k_run)
    return SavnRunner(params, optimizer.init(params), k_run, jnp.int32(0),
                      init_rows(cfg, model, params["nav"], scenes, k_rows))


def make_savn_chunk(cfg, model, learned, optimizer):
    """A jitted (runner, scenes) -> (runner, metrics) of cfg.updates_per_chunk SAVN
    updates; metrics as training.update's chunk (EpisodeStats sums over the episodes that
    ended, loss terms)."""
    grad_fn = jax.value_and_grad(savn_loss, has_aux=True)

    @jax.jit
    def chunk(runner: SavnRunner, scenes):
        def one(carry, _):
            runner, stats = carry
            key, k = jax.random.split(runner.key)
            (loss, (aux, ep, rows)), grads = grad_fn(runner.params, runner.rows, model,
                                                     learned, cfg, scenes, k)
            updates, opt_state = optimizer.update(grads, runner.opt_state, runner.params)
            runner = SavnRunner(optax.apply_updates(runner.params, updates), opt_state, key,
                                runner.update + 1, rows)
            stats = jax.tree_util.tree_map(jnp.add, stats, ep)
            return (runner, stats), dict(aux, loss=loss, grad_norm=optax.tree.norm(grads))

        (runner, stats), aux = jax.lax.scan(one, (runner, EpisodeStats.zeros()), None,
                                            length=cfg.updates_per_chunk)
        real = aux.pop("env_steps_real").sum()
        metrics = {k: v.mean() for k, v in aux.items()}
        metrics["loss_finite"] = jnp.isfinite(aux["loss"]).all()
        metrics.update(episodes=stats.count, success=stats.success, spl=stats.spl,
                       ret=stats.ret, length=stats.length, env_steps_real=real)
        return runner, metrics

    return chunk


@struct.dataclass
class SavnCarry:
    """Per-episode state of the test-time policy (leading axis B)."""
    lstm: Any            # the LSTM carry
    fast: Fast           # the episode's fast weights
    seg_lstm: Any        # the LSTM carry at the start of the running segment
    seg_inputs: Any      # ModelInputs (B, k, ...) of the running segment's steps
    steps: jax.Array     # (B,) index of the step in the episode
    updates: jax.Array   # (B,) inner steps taken in the episode


@compiled_once
def savn_policy(model, learned: LearnedLoss, k: int, inner_steps: int, inner_lr: float,
                widths: tuple[int, int, int], name: str = "SAVN",
                act_rule: str = "greedy") -> Policy:
    """Greedy (or, act_rule "sample", sampled: the release's agents/agent.py:120)
    actions with SAVN's test-time inner steps: after each of the first
    `inner_steps` segments of k steps of an episode, one SGD step (inner_lr) of the
    learned loss on that episode's fast weights (reset at each episode start).
    policy_params = {"nav", "ll"}; widths = scene_widths(scenes) (the segment buffer)."""
    v_segment = partial(segment_rows, model)
    v_inner = partial(inner_rows, model, learned, first_order=True)
    slots = max(inner_steps * k, 1)

    def init(batch, params):
        nav = params["nav"]
        return SavnCarry(model.initial_carry(batch), init_fast(nav, batch, slots),
                         model.initial_carry(batch), zero_inputs(widths, batch, k),
                         jnp.zeros(batch, jnp.int32), jnp.zeros(batch, jnp.int32))

    def act(params, carry: SavnCarry, obs, key, scenes, fresh):
        nav = params["nav"]
        shared, _ = split_params(nav)
        steps = jnp.where(fresh, 0, carry.steps + 1)
        updates = jnp.where(fresh, 0, carry.updates)
        fast = reset_fast(nav, carry.fast, fresh)
        lstm = reset_carry(carry.lstm, fresh)
        pos = steps % k
        seg_lstm = where_rows(pos == 0, lstm, carry.seg_lstm)
        inputs = model_inputs(scenes, obs)
        inputs = inputs._replace(prev_action=previous_action(model, inputs.prev_action, lstm))
        seg_inputs = jax.vmap(lambda buf, x, i: jax.tree_util.tree_map(
            lambda b, y: b.at[i].set(y), buf, x))(carry.seg_inputs, inputs, pos)
        one_step = jax.tree_util.tree_map(lambda x: x[:, None], inputs)
        logits, _, _, lstm, _, _ = v_segment(shared, fast.dense, fast.ux, fast.uh, fast.v,
                                             lstm, one_step, fast.zero_pert(1))
        action = choose({"greedy": lambda: jnp.argmax(logits[:, 0], -1),
                         "sample": lambda: jax.random.categorical(key, logits[:, 0])},
                        act_rule, "SAVN test-time actions (savn_act)")().astype(jnp.int32)
        on = (pos == k - 1) & (updates < inner_steps)

        def inner(fast):
            *_, dense, ux, uh, v = v_inner(shared, fast.dense, fast.ux, fast.uh, fast.v,
                                           seg_lstm, seg_inputs, params["ll"], inner_lr,
                                           jnp.minimum(updates, inner_steps - 1) * k, on)
            return Fast(dense, ux, uh, v)                 # unchanged where not `on`

        if inner_steps > 0:
            fast = jax.lax.cond(on.any(), inner, lambda f: f, fast)
        return action, SavnCarry(lstm, fast, seg_lstm, seg_inputs, steps,
                                 updates + on.astype(jnp.int32))

    return Policy(name, init, act)


def run_policy(cfg, model, scenes) -> Policy:
    """The test-time SAVN policy of a SAVN run's config (the learned loss only, no
    reward); `scenes`: any split of the run's scene set (for its feature widths)."""
    return savn_policy(model, build_learned_loss(), cfg.savn_steps, cfg.savn_inner_steps,
                       cfg.savn_inner_lr, scene_widths(scenes),
                       f"{cfg.model}+SAVN" + ("-greedy" if cfg.savn_act == "greedy" else ""),
                       cfg.savn_act)


def scene_widths(scenes) -> tuple[int, int, int]:
    """(global_dim, categories, appearance_dim) of a SceneSet: savn_policy's `widths`."""
    return (int(scenes.global_dim), int(scenes.present.shape[-1]), int(scenes.appearance_dim))


def zero_inputs(widths: tuple[int, int, int], batch: int, k: int):
    """Zero ModelInputs (batch, k, ...) for scenes of these widths."""
    G, C, d = widths
    z = lambda *s: jnp.zeros((batch, k) + s)
    return ModelInputs(z(FEATURE_GRID, FEATURE_GRID, G), z(C, d), z(C, 4), z(C), z(C),
                       z(NUM_ACTIONS))
