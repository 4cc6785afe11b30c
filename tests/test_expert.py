"""Expert tables: JAX Bellman-Ford against a networkx BFS, and on hand-made graphs."""

from __future__ import annotations

import jax.numpy as jnp
import networkx as nx
import numpy as np

from orgnav_jax import constants as K
from orgnav_jax import scenes
from orgnav_jax.scenes.sceneset import expert


def _reverse_graph(next_state: np.ndarray) -> nx.DiGraph:
    """The reversed graph of the 5 moving actions (Done excluded), self-loops dropped."""
    rev = nx.DiGraph()
    rev.add_nodes_from(range(len(next_state)))
    for a in range(K.DONE):
        rev.add_edges_from((int(t), s) for s, t in enumerate(next_state[:, a]) if t != s)
    return rev


def _bfs_dist(rev: nx.DiGraph, sources: np.ndarray) -> np.ndarray:
    """Multi-source BFS (from the visible states) on the reversed graph; -1 = unreachable."""
    out = np.full(rev.number_of_nodes(), -1, np.int64)
    src = np.flatnonzero(sources).tolist()
    if not src:
        return out
    for d, layer in enumerate(nx.bfs_layers(rev, src)):
        out[layer] = d
    return out


def test_expert_matches_networkx_bfs_on_every_state(tiny_scenes):
    s = tiny_scenes
    nxt = np.asarray(s.next_state)
    vis, dist, act = np.asarray(s.visible), np.asarray(s.dist), np.asarray(s.expert_action)
    covered = np.zeros(s.num_states, int)
    for n in range(s.num_scenes):
        rows = s.state_slice(n)
        covered[rows] += 1
        name = s.scene_names[n]
        local = nxt[rows] - rows.start          # the room's graph, in its own indices
        assert ((local >= 0) & (local < rows.stop - rows.start)).all(), name
        rev = _reverse_graph(local)
        for c in range(K.NUM_CATEGORIES):
            want = _bfs_dist(rev, vis[rows, c])
            got = dist[rows, c].astype(np.int64)
            reach = want >= 0
            np.testing.assert_array_equal(got[reach], want[reach], err_msg=f"{name} c={c}")
            assert (got[~reach] == scenes.UNREACHABLE).all(), f"{name} c={c}"
            assert (act[rows, c][~reach] == scenes.NO_ACTION).all(), f"{name} c={c}"
    assert (covered == 1).all()     # every flat state belongs to exactly one room


def test_expert_actions_follow_shortest_paths(tiny_scenes):
    s = tiny_scenes
    nxt = np.asarray(s.next_state)                       # (T, A) global flat indices
    dist = np.asarray(s.dist).astype(np.int64)           # (T, C)
    act = np.asarray(s.expert_action).astype(np.int64)
    reach = dist < scenes.UNREACHABLE
    # never action 0 (MoveAhead) as a stand-in for "nothing": sentinels exactly where
    # unreachable
    assert ((act == scenes.NO_ACTION) == ~reach).all()
    assert scenes.NO_ACTION not in range(K.NUM_ACTIONS)
    assert scenes.UNREACHABLE > s.max_states
    at_goal = reach & (dist == 0)
    assert (act[at_goal] == K.DONE).all()
    np.testing.assert_array_equal(at_goal, np.asarray(s.visible))
    moving = reach & (dist > 0)
    s_i, c_i = np.nonzero(moving)
    a = act[s_i, c_i]
    assert ((a >= 0) & (a < K.DONE)).all()
    succ = nxt[s_i, a]
    np.testing.assert_array_equal(s.state_scene[succ], s.state_scene[s_i])  # same room
    np.testing.assert_array_equal(dist[succ, c_i], dist[s_i, c_i] - 1)
    assert (succ != s_i).all()
    # lowest-index optimal action (documented tie-break)
    for b in range(K.DONE):
        better = dist[nxt[s_i, b], c_i] == dist[s_i, c_i] - 1
        assert not (better & (b < a)).any()


def test_targets_of_room_type_mostly_reachable(tiny_scenes):
    s = tiny_scenes
    dist = np.asarray(s.dist)
    ok = total = 0
    for n in range(s.num_scenes):
        rt = K.ROOM_TYPES[int(s.room_type[n])]
        for name in K.TARGETS[rt]:
            c = K.category_index(name)
            if not s.present[n, c]:
                continue
            total += 1
            ok += bool((dist[s.state_slice(n), c] < scenes.UNREACHABLE).all())
    assert total > 0 and ok / total > 0.85


def _chain(S: int, visible_at: dict[int, list[int]]):
    """A 1-D chain: MoveAhead s -> s+1, RotateLeft s -> s-1 (ends stay); the other
    actions stay. visible_at: category -> states where it is visible."""
    s = np.arange(S)
    nxt = np.tile(s[:, None], (1, K.NUM_ACTIONS))
    nxt[:, K.MOVE_AHEAD] = np.minimum(s + 1, S - 1)
    nxt[:, K.ROTATE_LEFT] = np.maximum(s - 1, 0)
    vis = np.zeros((S, K.NUM_CATEGORIES), bool)
    for c, states in visible_at.items():
        vis[states, c] = True
    return nxt, vis, np.ones(S, bool)


def test_expert_tables_on_chain():
    # room 0: a 5-state chain plus one padding state (self-loops, marked visible for
    # category 3, which must be ignored); room 1: a 6-state chain
    nxt1, vis1, ok1 = _chain(5, {0: [4], 1: [0, 4]})
    pad_vis = np.zeros((1, K.NUM_CATEGORIES), bool)
    pad_vis[0, 3] = True
    nxt1 = np.concatenate([nxt1, np.full((1, K.NUM_ACTIONS), 5)])
    vis1 = np.concatenate([vis1, pad_vis])
    ok1 = np.append(ok1, False)
    nxt2, vis2, ok2 = _chain(6, {0: [0], 2: [2]})
    d, a = expert.expert_tables(jnp.asarray(np.stack([nxt1, nxt2]), jnp.int32),
                                jnp.asarray(np.stack([vis1, vis2])),
                                jnp.asarray(np.stack([ok1, ok2])))
    d, a = np.asarray(d), np.asarray(a)
    U, X = scenes.UNREACHABLE, scenes.NO_ACTION
    M, L, D = K.MOVE_AHEAD, K.ROTATE_LEFT, K.DONE
    np.testing.assert_array_equal(d[0, :, 0], [4, 3, 2, 1, 0, U])
    np.testing.assert_array_equal(a[0, :, 0], [M, M, M, M, D, X])
    np.testing.assert_array_equal(d[0, :, 1], [0, 1, 2, 1, 0, U])
    np.testing.assert_array_equal(a[0, :, 1], [D, L, M, M, D, X])   # tie at 2 -> MoveAhead
    # visible only on a padding state: ignored
    np.testing.assert_array_equal(d[0, :, 3], [U] * 6)
    np.testing.assert_array_equal(a[0, :, 3], [X] * 6)
    np.testing.assert_array_equal(d[1, :, 0], [0, 1, 2, 3, 4, 5])
    np.testing.assert_array_equal(a[1, :, 0], [D, L, L, L, L, L])
    np.testing.assert_array_equal(d[1, :, 2], [2, 1, 0, 1, 2, 3])
    np.testing.assert_array_equal(a[1, :, 2], [M, M, D, L, L, L])
    # categories never visible: unreachable everywhere
    for n, c in [(0, 2), (1, 1), (1, 21)]:
        assert (d[n, :, c] == U).all() and (a[n, :, c] == X).all()


def test_expert_tables_long_chain_converges():
    """Distances up to S-1 need S-1 relaxation rounds."""
    S = 300
    nxt, vis, ok = _chain(S, {7: [S - 1]})
    d, a = expert.expert_tables(jnp.asarray(nxt[None], jnp.int32), jnp.asarray(vis[None]),
                                jnp.asarray(ok[None]))
    np.testing.assert_array_equal(np.asarray(d)[0, :, 7], S - 1 - np.arange(S))
    assert (np.asarray(a)[0, :-1, 7] == K.MOVE_AHEAD).all()


def test_expert_ignores_done_and_one_way_edges():
    """Done never moves; a one-way edge (s -> t) does not give t a path back to s."""
    S = 4
    nxt = np.tile(np.arange(S)[:, None], (1, K.NUM_ACTIONS))
    nxt[0, K.MOVE_AHEAD] = 1      # 0 -> 1 only
    nxt[1, K.LOOK_DOWN] = 2       # 1 -> 2
    nxt[3, K.DONE] = 2            # a (malformed) Done edge must not be used
    vis = np.zeros((S, K.NUM_CATEGORIES), bool)
    vis[2, 0] = True
    d, a = expert.expert_tables(jnp.asarray(nxt[None], jnp.int32), jnp.asarray(vis[None]),
                                jnp.asarray(np.ones((1, S), bool)))
    np.testing.assert_array_equal(np.asarray(d)[0, :, 0],
                                  [2, 1, 0, scenes.UNREACHABLE])
    np.testing.assert_array_equal(np.asarray(a)[0, :, 0],
                                  [K.MOVE_AHEAD, K.LOOK_DOWN, K.DONE, scenes.NO_ACTION])


def test_expert_tables_compiles_once_for_same_shapes(monkeypatch):
    """Repeated calls with the same shapes reuse the compiled function."""
    traces = []
    original = expert._room_tables

    def counting(*args):
        traces.append(1)
        return original(*args)

    monkeypatch.setattr(expert, "_room_tables", counting)
    S = 37  # a shape no other test uses
    for k in range(3):
        nxt, vis, ok = _chain(S, {k: [k]})
        d, _ = expert.expert_tables(jnp.asarray(nxt[None], jnp.int32), jnp.asarray(vis[None]),
                                    jnp.asarray(ok[None]))
        assert int(d[0, S - 1, k]) == S - 1 - k
    assert len(traces) == 1
    nxt, vis, ok = _chain(S + 1, {0: [0]})
    expert.expert_tables(jnp.asarray(nxt[None], jnp.int32), jnp.asarray(vis[None]),
                         jnp.asarray(ok[None]))
    assert len(traces) == 2   # a new shape traces again (the counter is live)


def test_targets_and_state_count_fields(tiny_scenes):
    s = tiny_scenes
    counts = np.asarray(s.state_count)
    offsets = np.asarray(s.state_offset)
    assert counts.sum() == s.num_states
    order = np.argsort(offsets)                 # the rooms' runs tile the flat axis
    np.testing.assert_array_equal(offsets[order], np.cumsum(counts[order]) - counts[order])
    targets = np.asarray(s.targets)
    dist = np.asarray(s.dist)
    for n in range(s.num_scenes):
        rt = K.ROOM_TYPES[int(s.room_type[n])]
        for c in range(K.NUM_CATEGORIES):
            d = dist[offsets[n]:offsets[n] + counts[n], c]
            want = (K.CATEGORIES[c] in K.TARGETS[rt] and bool(s.present[n, c])
                    and bool((d < scenes.UNREACHABLE).any()))
            assert bool(targets[n, c]) == want, (s.scene_names[n], K.CATEGORIES[c])
            if want:  # reachable from every valid state (the state graph is connected)
                assert (d < scenes.UNREACHABLE).all()
        assert targets[n].sum() >= 0.7 * len(K.TARGETS[rt]), s.scene_names[n]
