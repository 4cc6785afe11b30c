"""The experiments as a library: what the tables, claims, sweeps and their checks are
made of (experiments/ holds thin command lines over it; docs/results.md).

    convergence  the rule that says when a row has stopped learning, and the trainer's
                 stop criterion built on it (--until-converged)
"""
