"""A table's spec: its one definition (JSON: out, rows, seeds, config overrides, tpn
fields; optionally about, population, converged and extends), e.g.
experiments/tables/table_5m.json, copied to OUT/spec.json when the table is made.
`"converged": true` asks the table to judge every trained row by the convergence rule
(tables/convergence.py) at its budget: OUT/convergence.md (table_files). `"extends":
BASE` makes the table of BASE's rows at convergence: rows the rule says have not
converged in BASE train on from its runs under the stop criterion, config's
total_env_steps the cap (tables/extend.py)."""

from __future__ import annotations

import json
from pathlib import Path

from orgnav_jax.constants import DEFAULT_SCENE_PRESET, ROOM_TYPES
from orgnav_jax.errors import INT32_MAX, is_int, shown
from orgnav_jax.tables.convergence import MIN_SEEDS, MIN_VAL_EPISODES
from orgnav_jax.tables.rows import parse_row
from orgnav_jax.tpn.config import get_tpn_config
from orgnav_jax.training.config import get_config

SPEC_KEYS = {"out": str, "rows": list, "seeds": list, "config": dict, "tpn": dict}
SPEC_OPTIONAL = {"about": str, "population": bool, "converged": bool, "extends": str}


def read_spec(path: str | Path) -> dict:
    """A table spec (JSON: out, rows, seeds, config, tpn; optionally about, population,
    converged, extends) -> dict; ValueError naming the file and the field otherwise (with
    "converged": true, also where the rule could not judge its rows: check_rule_applies)."""
    if Path(path).is_dir():
        raise ValueError(f"table spec {path}: a directory, expected a JSON file")
    try:
        spec = json.loads(Path(path).read_text())
    except ValueError as err:
        raise ValueError(f"table spec {path}: not JSON ({err})") from None
    if not isinstance(spec, dict):
        raise ValueError(f"table spec {path}: expected a JSON object")
    for key, kind in SPEC_KEYS.items():
        if key not in spec or not isinstance(spec[key], kind):
            raise ValueError(f"table spec {path}: field {key!r} missing or not a "
                             f"{kind.__name__}")
    unknown = sorted(set(spec) - set(SPEC_KEYS) - set(SPEC_OPTIONAL))
    if unknown:
        raise ValueError(f"table spec {path}: unknown field(s) {unknown}")
    for key, kind in SPEC_OPTIONAL.items():
        if key in spec and not isinstance(spec[key], kind):
            raise ValueError(f"table spec {path}: field {key!r} is not a {kind.__name__}")
    if not spec["rows"]:
        raise ValueError(f"table spec {path}: field 'rows': expected at least one row")
    for row in spec["rows"]:
        if not isinstance(row, str):
            raise ValueError(f"table spec {path}: field 'rows': expected row names "
                             f"(strings), got {row!r}")
        try:
            parse_row(row)
        except ValueError as err:
            raise ValueError(f"table spec {path}: field 'rows': {err}") from None
    if not spec["seeds"] or not all(is_int(x) and 0 <= x <= INT32_MAX for x in spec["seeds"]):
        raise ValueError(f"table spec {path}: field 'seeds': expected integers >= 0, got "
                         f"{shown(spec['seeds'])}")
    for key in ("rows", "seeds"):
        if len(set(spec[key])) != len(spec[key]):
            raise ValueError(f"table spec {path}: field {key!r}: an entry appears twice")
    if not spec["out"]:
        raise ValueError(f"table spec {path}: field 'out': expected a directory, got ''")
    cfg = get_config("baseline", **spec["config"])    # names a bad field or value
    get_tpn_config(base_dir="runs/x", **spec["tpn"])
    if spec.get("converged"):
        check_rule_applies(path, spec, cfg.eval_episodes_per_room_type)
    if "extends" in spec:
        base = Path(spec["extends"]) / "spec.json"
        if not base.is_file():
            raise ValueError(f"table spec {path}: field 'extends': {base} missing (expected "
                             "the directory of a table run_table.py made)")
        check_extends(path, spec, read_spec(base))
    return spec


def check_rule_applies(path: str | Path, spec: dict, eval_episodes_per_room_type: int
                       ) -> None:
    """A spec with "converged": true: ValueError (one line, naming the file and the field)
    unless its rows' seeds train in one program (population), there are at least
    MIN_SEEDS of them and each val evaluation has at least MIN_VAL_EPISODES episodes."""
    need = "\"converged\": true (the convergence rule) needs"
    if spec.get("population") is not True:
        raise ValueError(f"table spec {path}: field 'population': {need} the seeds of a "
                         "row trained in one program: \"population\": true")
    if len(spec["seeds"]) < MIN_SEEDS:
        raise ValueError(f"table spec {path}: field 'seeds': {need} at least {MIN_SEEDS} "
                         f"seeds, got {len(spec['seeds'])}")
    episodes = eval_episodes_per_room_type * len(ROOM_TYPES)
    if episodes < MIN_VAL_EPISODES:
        raise ValueError(f"table spec {path}: field 'config': eval_episodes_per_room_type "
                         f"{eval_episodes_per_room_type} gives val evaluations of {episodes:,}"
                         f" episodes; {need} at least {MIN_VAL_EPISODES:,} (250 per room "
                         "type)")


def check_extends(path, spec: dict, base_spec: dict) -> None:
    """ValueError (one line, naming the spec file and the field) unless the spec can
    extend the table base_spec defines: the rule's table ("converged": true), a
    different out, the same seeds, rows among BASE's, the same config but for a larger
    total_env_steps (the cap), the same tpn fields."""
    where = f"table spec {path}"
    base = spec["extends"]
    if not spec.get("converged"):
        raise ValueError(f"{where}: field 'converged': \"extends\" trains rows on under the "
                         "convergence rule: expected \"converged\": true")
    if Path(base).resolve() == Path(spec["out"]).resolve():
        raise ValueError(f"{where}: field 'extends': {base} is the table's own out; "
                         "expected another table's directory")
    if spec["seeds"] != base_spec["seeds"]:
        raise ValueError(f"{where}: field 'seeds': {spec['seeds']} differs from {base}'s "
                         f"{base_spec['seeds']}; an extended table has the seeds of its base")
    extra = [r for r in spec["rows"] if r not in base_spec["rows"]]
    if extra:
        raise ValueError(f"{where}: field 'rows': {extra[0]} is not a row of {base}")
    if spec["tpn"] != base_spec["tpn"]:
        raise ValueError(f"{where}: field 'tpn': {spec['tpn']} differs from {base}'s "
                         f"{base_spec['tpn']}")
    ours, theirs = dict(spec["config"]), dict(base_spec["config"])
    cap = ours.pop("total_env_steps", None)
    theirs.pop("total_env_steps", None)
    if ours != theirs:
        field = sorted(k for k in set(ours) | set(theirs) if ours.get(k) != theirs.get(k))[0]
        raise ValueError(f"{where}: field 'config': {field} {ours.get(field)!r} differs from "
                         f"{base}'s {theirs.get(field)!r}; an extended table changes only "
                         "total_env_steps (the cap)")
    budget = get_config("baseline", **base_spec["config"]).total_env_steps
    if cap is None or cap <= budget:
        raise ValueError(f"{where}: field 'config': total_env_steps {cap} is the cap of the "
                         f"extended rows: expected more than {base}'s {budget:,}")


def read_table_spec(out: Path) -> dict:
    """TABLE/spec.json of a table directory (ValueError naming what is missing)."""
    if not out.is_dir():
        raise ValueError(f"{out}: not a directory (expected a run_table.py output "
                         "directory with spec.json)")
    spec_path = out / "spec.json"
    if not spec_path.is_file():
        raise ValueError(f"{spec_path}: missing (run_table.py --spec writes it)")
    return read_spec(spec_path)


def table_scenes(config: dict) -> str:
    """The scenes a table's runs are on (its spec's config, or run_table.py's options),
    named as api.evaluate tags results ('scenes'): the scenes_dir folder's name, else the
    scene_preset, else the default scene preset (what a config naming none trains on:
    `small` before 2026-12-05, `calibrated` since; the tables made before name theirs)."""
    if config.get("scenes_dir"):
        return Path(config["scenes_dir"]).name
    return config.get("scene_preset", DEFAULT_SCENE_PRESET)
