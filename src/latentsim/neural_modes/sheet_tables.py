r"""Tables of the Neural Modes sheet study (Wang et al. 2024, Tables 2, 3, 4, A1; Figs. 3, 4), ours beside the paper's.

:func:`tables` turns a ``sheet.run_sheet_study`` result into pandas DataFrames: each method at the
checkpoint its stopping criterion chose (the supervised methods at the least validation L2, Neural
Modes at the last epoch), with the paper's numbers in adjacent ``*_paper*`` columns;
:func:`tables_over_seeds` puts the tables of several seeds' studies together: medians, and the headline
errors' least and largest over the seeds.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from latentsim.neural_modes.metrics import METRICS, STOPPING
from latentsim.neural_modes.sheet import SUPERVISED

__all__ = ["PAPER_TABLE2", "PAPER_TABLE3", "PAPER_TABLE4", "PAPER_TABLEA1", "SPREAD_COLUMNS", "STOPPING_LABEL", "tables", "tables_over_seeds"]

# Paper numbers (Wang et al. 2024), for the adjacent columns.
PAPER_TABLE2 = {  # method: (val dE_avg, dE_max, dE_std, E_avg, test dE_avg, dE_max, dE_std, E_avg)
    "PCA+AE": (1814, 22225, 2005, 18144, 2259, 27991, 2646, 24007),
    "PCA+AE (grid)": (2188, 36168, 3626, 18088, 2649, 72834, 4664, 23217),
    "L2 Supervised": (1630, 10231, 1148, 18210, 2074, 13750, 1697, 24325),
    "Neural Modes (stoch.)": (376, 1197, 170, 17032, 386, 1154, 183, 22891),
    "Neural Modes (grid)": (199, 754, 118, 16831, 245, 3062, 215, 22730),
}
PAPER_TABLE2["Neural Modes (grid, penalty, as the paper)"] = PAPER_TABLE2["Neural Modes (grid)"]  # the paper's own formulation
PAPER_TABLE4 = {  # x1e6: weighted dS_avg, dS_max, dS_std, |S|_avg, max-over-elements dS_avg, dS_max, dS_std, |S|_avg
    "PCA+AE": (25, 138, 17, 251, 67, 431, 49, 520),
    "PCA+AE (grid)": (25, 305, 29, 245, 64, 784, 68, 505),
    "L2 Supervised": (25, 100, 14, 255, 87, 350, 57, 550),
    "Neural Modes (stoch.)": (9, 36, 7, 240, 22, 155, 21, 486),
    "Neural Modes (grid)": (6, 24, 5, 236, 16, 124, 16, 479),
}
PAPER_TABLE4["Neural Modes (grid, penalty, as the paper)"] = PAPER_TABLE4["Neural Modes (grid)"]
PAPER_TABLEA1 = {  # x1e4: ||dF||_1, ||dF||_2, ||F||_1, ||F||_2
    "PCA+AE": (111, 5.95, 279, 24),
    "PCA+AE (grid)": (83, 4.35, 250, 22),
    "L2 Supervised": (125, 6.59, 293, 24),
    "Neural Modes (stoch.)": (31, 0.93, 199, 19),
    "Neural Modes (grid)": (25, 0.74, 193, 19),
}
PAPER_TABLEA1["Neural Modes (grid, penalty, as the paper)"] = PAPER_TABLEA1["Neural Modes (grid)"]
PAPER_TABLE3 = {  # E_avg at the epoch chosen by each stopping criterion: val (L2, energy), test (L2, energy)
    "PCA+AE": (18144, 17762, 24007, 23484),
    "PCA+AE (grid)": (18088, 18042, 23217, 23051),
    "L2 Supervised": (18210, 17690, 24325, 23682),
}


STOPPING_LABEL = {"final": "last epoch", "val_l2": "validation L2", "val_energy": "validation energy"}


def _at(method: dict, part: str, criterion: str) -> dict:
    """{metric: value} of a method's ``part`` (val | test) at the checkpoint chosen by ``criterion``."""
    return dict(zip(METRICS, np.asarray(method[part])[int(method[f"stop_{criterion}"])]))


def _table2_row(head: dict, r: dict, crit: str) -> dict:
    """Table 2: energy error on the validation and test sets."""
    p2 = PAPER_TABLE2.get(head["method"])
    row = dict(head)
    for i, s in enumerate(("val", "test")):
        v = _at(r, s, crit)
        for j, key in enumerate(("dE_avg", "dE_max", "dE_std", "E_avg")):
            row[f"{s}_{key}"] = v[key]
            row[f"{s}_{key}_paper"] = p2[4 * i + j] if p2 else np.nan
    row["test_E_gt"] = _at(r, "test", crit)["E_gt"]
    return row


def _table4_row(head: dict, v: dict) -> dict:
    """Table 4: membrane stress error on the test set, area-weighted mean and max over elements."""
    p4 = PAPER_TABLE4.get(head["method"])
    row = dict(head)
    for i, (red, short) in enumerate((("stress_weighted", "Sw"), ("stress_max", "Sm"))):
        for j, key in enumerate(("dS_avg", "dS_max", "dS_std", "S_avg")):
            row[f"{red}_{key}"] = v[key.replace("S", short, 1)]
            row[f"{red}_{key}_paper_x1e6"] = p4[4 * i + j] if p4 else np.nan
    return row


def _tableA1_row(head: dict, v: dict) -> dict:
    """Table A1: nodal force error on the test set."""
    pa = PAPER_TABLEA1.get(head["method"])
    row = dict(head)
    for j, key in enumerate(("dF_l1", "dF_l2", "F_l1", "F_l2")):
        row[key] = v[key]
        row[f"{key}_paper_x1e4"] = pa[j] if pa else np.nan
    return row


def _table3_row(label: str, r: dict) -> dict:
    """Table 3: a supervised method's energy at the epoch of each stopping criterion."""
    row = {"method": label}
    p3 = PAPER_TABLE3.get(label)
    for i, s in enumerate(("val", "test")):
        for j, c in enumerate(STOPPING):
            at = _at(r, s, c)
            row[f"{s}_E_avg_{c}"] = at["E_avg"]
            row[f"{s}_E_avg_{c}_paper"] = p3[2 * i + j] if p3 else np.nan
            row[f"{s}_dE_avg_{c}"] = at["dE_avg"]
    for c in STOPPING:
        row[f"epoch_{c}"] = int(r["epochs"][int(r[f"stop_{c}"])])
    row["epoch_last"] = int(r["epochs"][-1])
    row["test_E_avg_last"] = _at(r, "test", "final")["E_avg"]
    return row


def tables(study: dict) -> dict:
    """pandas DataFrames of Tables 2, 3, 4, A1 (ours beside the paper's), the correlation eigenvalues
    (Fig. 4) and the latent structure (origin, symmetry; Fig. 3) of a ``sheet.run_sheet_study`` result."""
    if list(study["metrics"]) != list(METRICS):
        raise ValueError(f"the study's metrics {list(study['metrics'])} are not this version's {list(METRICS)}; rerun the study")
    t2, t3, t4, ta1, structure = [], [], [], [], []
    for slug, r in study["methods"].items():
        label, crit = r["label"], r["table_stopping"]
        head = {"method": label, "stopping": STOPPING_LABEL[crit], "epoch": int(r["epochs"][int(r[f"stop_{crit}"])])}
        t2.append(_table2_row(head, r, crit))
        v = _at(r, "test", crit)
        t4.append(_table4_row(head, v))
        ta1.append(_tableA1_row(head, v))
        if slug in SUPERVISED:
            t3.append(_table3_row(label, r))
        structure.append({"method": label, "epoch": head["epoch"], "origin |n(0) - X| / |X|": r["origin_relative_error"],
                          "symmetry error mean": r["symmetry_mean"], "symmetry error max": r["symmetry_max"]})  # fmt: skip
    g = study["ground_truth"]
    structure.append({"method": "ground truth (Eq. 9)", "epoch": np.nan, "origin |n(0) - X| / |X|": 0.0,
                      "symmetry error mean": g["symmetry_mean"], "symmetry error max": g["symmetry_max"]})  # fmt: skip
    corr = [
        {"method": c["label"], "eigenvalues": " ".join(f"{w:.3f}" for w in c["eigenvalues"]), "min": float(np.min(c["eigenvalues"])), "max": float(np.max(c["eigenvalues"]))}
        for c in study["correlation"].values()
    ]
    return {
        "table2": pd.DataFrame(t2), "table3": pd.DataFrame(t3), "table4": pd.DataFrame(t4), "tableA1": pd.DataFrame(ta1),
        "correlation": pd.DataFrame(corr), "structure": pd.DataFrame(structure),
    }  # fmt: skip


# the headline errors of each table, which get their least and largest over the seeds beside the median
SPREAD_COLUMNS = {
    "table2": ("val_dE_avg", "test_dE_avg", "test_dE_max", "test_E_avg"),
    "table3": ("test_E_avg_val_l2", "test_E_avg_val_energy"),
    "table4": ("stress_weighted_dS_avg", "stress_max_dS_avg"),
    "tableA1": ("dF_l1", "dF_l2"),
    "correlation": ("min",),
    "structure": ("symmetry error mean",),
}


def tables_over_seeds(per_seed: list, seeds) -> dict:
    """:func:`tables` of several seeds' studies as one set of tables: one row per method (in the first seed's
    order), every number the median over the seeds (the paper's columns are the same in each), a column
    ``seeds``, and the :data:`SPREAD_COLUMNS` with their least and largest (``<name>_min``, ``<name>_max``)
    right after them.  Text columns are the first seed's (the correlation's ``eigenvalues``: the first seed's
    list).  One seed: its tables, with ``seeds`` 1 and no spread columns."""
    seeds = list(seeds)
    if len(per_seed) != len(seeds) or not per_seed:
        raise ValueError(f"tables_over_seeds: {len(per_seed)} seeds' tables for seeds {seeds}")
    out = {}
    for name, first in per_seed[0].items():
        if first.empty:
            out[name] = first
            continue
        tabs = [p[name] for p in per_seed]
        for k, t in enumerate(tabs[1:], 1):
            if list(t["method"]) != list(first["method"]):
                raise ValueError(f"{name}: seed {seeds[k]} has the methods {list(t['method'])}, seed {seeds[0]} {list(first['method'])}")
        rows = []
        for i in range(len(first)):
            row = {}
            for col in first.columns:
                values = [t.iloc[i][col] for t in tabs]
                numeric = all(isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool) for v in values)
                row[col] = float(np.median(np.asarray(values, dtype=float))) if numeric and len(tabs) > 1 else values[0]
                if col == "method":
                    row["seeds"] = len(tabs)
                if len(tabs) > 1 and col in SPREAD_COLUMNS.get(name, ()):
                    row[f"{col}_min"], row[f"{col}_max"] = float(np.min(values)), float(np.max(values))
            rows.append(row)
        out[name] = pd.DataFrame(rows)
    return out
