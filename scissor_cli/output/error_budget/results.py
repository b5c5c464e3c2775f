"""The error budget in results.h5 and its summary (docs/contract.md, `/budget`; docs/model.md §16).

`/budget/<row>/<target>/final_error` (T, 2) ((T, 3) in a 3-D scene), `.../miss_mm` (T,) or, with
insertion, (T, strategies), `.../failed` (T,) bool; `/budget/<row>` attrs:
the trial settings the row switched on. `/budget` attrs: `sources` (the rows,
`all` first: the run's own `/trials`), `profile`, `paper_max_mm`.
"""

from __future__ import annotations

from dataclasses import dataclass

import h5py
import numpy as np

from scissor_cli.output.results import ResultsFile, check_finite, finished_trials

#: the paper's Fig. 14 maxima, mm: rows prosthesis, ex vivo; columns |x| (across the push), |y| (along it)
PAPER_MAX_MM = np.array([[0.7, 1.7], [1.3, 2.5]])
PAPER_PROFILES = ("prosthesis", "ex_vivo")


def write_budget_row(out: ResultsFile, row: str, fields: dict, outcomes: dict[str, list]) -> None:
    """One row's trials per target (`trials.TrialOutcome`s in trial order), stored whole."""
    for target, trials in outcomes.items():
        ok = np.array([o is not None and o.ok for o in trials])
        dim = next((np.size(o.final_error) for o, k in zip(trials, ok) if k), 2)  # (3 in a 3-D scene)
        final = np.array([o.final_error if k else np.zeros(dim) for o, k in zip(trials, ok)], float).reshape(-1, dim)
        if any(o is not None and np.size(o.insertion_miss_mm) for o in trials):
            width = max(np.size(o.insertion_miss_mm) for o in trials if o is not None)
            miss = np.array([o.insertion_miss_mm if k else np.zeros(width) for o, k in zip(trials, ok)], float)
        else:
            miss = np.array([o.miss_mm if k else 0.0 for o, k in zip(trials, ok)], float)
        g = f"budget/{row}/{target}"
        check_finite(f"/{g}/final_error", final)
        check_finite(f"/{g}/miss_mm", miss)
        out.dataset(f"{g}/final_error", final, "mm", description="true minus desired, x and y (and z in 3-D)")
        out.dataset(f"{g}/miss_mm", miss, "mm", description="miss across the needle (per strategy with insertion)")
        out.dataset(f"{g}/failed", ~ok, description="trial crashed: its numbers are fill values")
    out.attrs(f"budget/{row}", fields)
    out.flush()


def write_budget_attrs(out: ResultsFile, rows: list[str], profile: str) -> None:
    out.attrs("budget", {"sources": ["all"] + list(rows), "profile": profile, "paper_max_mm": PAPER_MAX_MM,
                         "paper_profiles": list(PAPER_PROFILES)})
    out.flush()


@dataclass(frozen=True)
class BudgetCell:
    """One row and target: the finished trials' final errors (T, 2) and misses (T,) or (T, S), mm."""

    final_error: np.ndarray
    miss_mm: np.ndarray


def read_budget(h5: h5py.File) -> dict[str, dict[str, BudgetCell]]:
    """{row: {target: cell}} with `all` from /trials (finished trials only); {} without a budget."""
    if "budget" not in h5:
        return {}
    out: dict[str, dict[str, BudgetCell]] = {"all": {}}
    for target, g in h5["trials"].items():
        keep = finished_trials(g)
        miss = g["miss_mm"][:] if "miss_mm" in g else g["manipulation_miss_mm"][:]
        out["all"][target] = BudgetCell(g["final_error"][:][keep], miss[keep])
    for row in h5["budget"].attrs.get("sources", [])[1:]:
        if row not in h5["budget"]:
            continue  # not run yet (a killed run)
        out[row] = {t: BudgetCell(g["final_error"][:][~g["failed"][:]], g["miss_mm"][:][~g["failed"][:]])
                    for t, g in h5[f"budget/{row}"].items()}
    return out


def budget_rows(budget: dict[str, dict[str, BudgetCell]], strategy: int = -1) -> list[dict]:
    """Per row and target: |x|, |y| and miss (median, p95, max, mm) and the shares of the total variance and
    of the total mean square.

    variance_share: the row's variance of the final error (x and y summed)
    over the `all` row's: for independent sources the shares add up to about
    1 (what they leave is the sources' interaction). mean_square_share: the
    row's mean of |final error|² over the `all` row's, which also counts a
    bias: a source that moves every trial the same way (the slab truth's
    shortfall at the stroke limit) has no variance but may be most of the
    error. With insertion the miss is that of one strategy (`strategy`,
    default the last in the config's order).
    """
    rows = []
    for row, cells in budget.items():
        for target, cell in cells.items():
            total = budget["all"].get(target)
            e = np.abs(cell.final_error)
            miss = cell.miss_mm if cell.miss_mm.ndim == 1 else cell.miss_mm[:, strategy]
            var_all, ms_all = (_variance(total.final_error), _mean_square(total.final_error)) if total is not None \
                else (0.0, 0.0)
            rec = {"source": row, "target": target, "trials": len(e)}
            axes = [("x", 0), ("y", 1)] + ([("z", 2)] if e.ndim == 2 and e.shape[1] == 3 else [])
            for name, values in [(a, e[:, i] if len(e) else e) for a, i in axes] + [("miss", miss)]:
                stats = (np.median(values), np.percentile(values, 95), np.max(values)) if len(values) else (0.0,) * 3
                rec.update({f"{name}_median_mm": float(stats[0]), f"{name}_p95_mm": float(stats[1]),
                            f"{name}_max_mm": float(stats[2])})
            rec["variance_share"] = _variance(cell.final_error) / var_all if var_all > 0 else 0.0
            rec["mean_square_share"] = _mean_square(cell.final_error) / ms_all if ms_all > 0 else 0.0
            rows.append(rec)
    return rows


def _variance(final_error: np.ndarray) -> float:
    """The variance over trials of final errors (K, 2), x and y summed (mm²); 0 without trials."""
    return float(np.var(final_error, axis=0).sum()) if len(final_error) else 0.0


def _mean_square(final_error: np.ndarray) -> float:
    """The mean over trials of |e|² (mm²) of final errors (K, 2); 0 without trials."""
    return float(np.mean(np.sum(final_error ** 2, axis=1))) if len(final_error) else 0.0
