"""The experiments as a library: what the tables, claims, sweeps and their checks are
made of (experiments/ holds thin command lines over it; docs/results.md, "The tables
library"). One job a module, lowest first:

    rows         a row's name BASE+VARIANT@LR taken apart once (Row), the rows there are
    layout       where a table's files lie: OUT/runs/<row>-s<seed>/...
    spec         a table's definition (spec.json), read and checked
    stats        the one statistics module: mean ± sample std, paired differences, t
                 interval (ddof 1), one-sided p, bootstrap, the three-level verdict
    pages        every generated file written (atomically) or compared (--check)
    runs         what a table reads from its runs: results JSONs (each summary recomputed
                 from its per-episode outcomes), metrics.jsonl's val records
    provenance   which code and machine made each run: records, provenance.md
    table        table.md
    claims       the paper's claims and claims.md, before/after, per category
    table_files  a table directory's generated files, made, written or checked
    sweeps       the val sweeps' records and their summary page
    choices      what val chose (choices.json, choices.md)
    calibration  the perception calibration's page
    adjacency    the learned adjacency's anchor-pair statistic, adjacency.json
    before_parity  the superseded investigations' pages (knob, 20 M, the TPN's budget)
    convergence  the rule that says when a row has stopped learning, and the trainer's
                 stop criterion built on it (--until-converged)
    convergence_page  the budget campaign's page: the rule per row, val by span of env
                 steps, a table's rows by tenth of their budget
    extend       a table extended to convergence (a spec's "extends"): each base row
                 carried over, trained on under the rule, or left until it finishes
"""
