"""Extract the numbers the golden test compares from a run's results.h5.

    python tests/golden/extract.py RUN_DIR OUT.npz

Keys are HDF5 paths (datasets, and attributes as PATH@ATTR) of what the
example scene's run produces: forward displacements and targets, Jacobians,
needle plans, and every trial's final error, iterations and history. Wall
times are left out: they are the only numbers a rerun may change.
"""

from __future__ import annotations

import sys
from pathlib import Path

import h5py
import numpy as np

#: prefixes of the groups whose numbers must not change, and the attributes that are not numbers of the model
GROUPS = ("forward", "jacobian", "plan", "trials", "targets", "mesh", "cups")
SKIP_ATTRS = {"time_s", "created", "units"}


def extract(results_h5: Path | str) -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    with h5py.File(results_h5, "r") as h5:
        def visit(name, obj):
            if not name.startswith(GROUPS):
                return
            if isinstance(obj, h5py.Dataset) and "time_s" not in name.split("/")[-1]:
                data = obj[()]
                if data.dtype.kind in "fiub":
                    out[name] = np.asarray(data, dtype=float)
            for key, value in obj.attrs.items():
                if key in SKIP_ATTRS:
                    continue
                arr = np.asarray(value)
                if arr.dtype.kind in "fiub":
                    out[f"{name}@{key}"] = arr.astype(float)

        h5.visititems(visit)
    return out


if __name__ == "__main__":
    run_dir, target = Path(sys.argv[1]), Path(sys.argv[2])
    data = extract(run_dir / "results.h5")
    np.savez_compressed(target, **data)
    print(f"{len(data)} arrays -> {target}")
