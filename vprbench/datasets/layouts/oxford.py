"""`netvlad-mat`: a NetVLAD-style dbStruct .mat naming database/query images and their positions.

The AnyLoc release of the Oxford RobotCar subsample (`Oxford_Robotcar/oxdatapart.mat` with
images under `oxDataPart/`) uses it: a cell array holding, in order, dbImage, locDb, qImage,
locQ, numDb, numQ, posDistThr, posDistSqThr. Image names have their spaces removed, as the
authors' loader does. NetVLAD's own files (e.g. `datasets/pitts30k_test.mat`: a struct with
named fields dbImageFns, utmDb, qImageFns, utmQ, posDistThr) are read by field name.
The manifest's radius (the paper's) wins over posDistThr.

Options: `mat` (file), `images` (folder the names are relative to). A name that leads out of that
folder (absolute, `..`, a symlink) is refused: the file could otherwise make vprbench read any image.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np

from ...errors import VPRBenchError
from ..manifest import DatasetManifest
from ..model import GroundTruth
from .base import from_manifest, inside, layout, require

#: seconds the MATLAB reader may take (the release's file reads in about a second)
READ_TIMEOUT_S = 300


def _plain_fields(path: str) -> dict:
    """The dbStruct's image names, positions and radius as JSON data (run in the child process)."""
    from scipy.io import loadmat

    contents = loadmat(path)
    if "dbStruct" not in contents:
        raise ValueError(f"it holds no variable 'dbStruct' (it holds {sorted(k for k in contents if not k.startswith('__'))})")
    loaded = contents["dbStruct"]
    names = ("db_image", "db_loc", "q_image", "q_loc", "num_db", "num_q", "radius")
    if loaded.dtype.names and "dbImageFns" in loaded.dtype.names:  # NetVLAD's named struct
        record = loaded.ravel()[0]
        fields = {k: record[n] for k, n in zip(names, ("dbImageFns", "utmDb", "qImageFns", "utmQ", "numImages", "numQueries", "posDistThr"))}
    else:  # a 1x8 cell array (as the release has it) or a struct: fields by position
        values = list(loaded.ravel()[0]) if loaded.dtype.names else list(loaded.ravel())
        if len(values) < len(names):
            raise ValueError(f"dbStruct has {len(values)} fields, expected at least {len(names)}")
        fields = dict(zip(names, values))
    plain = {k: [str(np.ravel(v)[0]).replace(" ", "") for v in np.ravel(fields[k])] for k in ("db_image", "q_image")}
    for k in ("db_loc", "q_loc"):
        locs = np.asarray(fields[k], dtype=np.float64)
        plain[k] = (locs.T if locs.shape[0] == 2 and locs.shape[1] != 2 else locs).tolist()  # NetVLAD's are 2xN
    plain["radius"] = float(np.ravel(fields["radius"])[0])
    return plain


def _child(path: str) -> None:
    """`python -c ...` entry: print the fields, or the error, as one JSON line."""
    try:
        answer = _plain_fields(path)
    except Exception as error:  # any failure of the parser on a damaged file; it builds data, never runs any
        answer = {"error": str(error) or type(error).__name__}
    print(json.dumps(answer))


def _read_in_child(path: Path) -> dict:
    """scipy's MATLAB reader is not hardened against damaged or crafted files (its documentation
    says so): some crash the process with a segmentation fault. It reads in a child process, so a
    crash is a message naming the file, not the end of vprbench without a word."""
    # -P: nothing imported from the working folder (a dataset folder's files are data, never code)
    command = [sys.executable, "-P", "-c", "import sys; from vprbench.datasets.layouts.oxford import _child; _child(sys.argv[1])",
               str(path)]
    # the same vprbench as this process: the folder holding its package first (a checkout run in place, a
    # worktree), then what the user's PYTHONPATH names
    package_parent = str(Path(__file__).resolve().parents[3])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [package_parent, os.environ.get("PYTHONPATH")]))}
    try:
        done = subprocess.run(command, stdin=subprocess.DEVNULL, capture_output=True, encoding="utf-8",
                              errors="replace", timeout=READ_TIMEOUT_S, env=env)
    except subprocess.TimeoutExpired:
        raise ValueError(f"reading it took more than {READ_TIMEOUT_S} s") from None
    if done.returncode < 0:
        raise ValueError(f"the MATLAB reader crashed on it ({signal.Signals(-done.returncode).name})")
    lines = done.stdout.strip().splitlines()
    if done.returncode or not lines:
        last = (done.stderr.strip().splitlines() or ["no output"])[-1]
        raise ValueError(f"the MATLAB reader failed ({last})")
    answer = json.loads(lines[-1])
    if "error" in answer:
        raise ValueError(answer["error"])
    return answer


def read_db_struct(path: Path) -> dict:
    try:
        fields = _read_in_child(path)
        images = {k: [str(name) for name in fields[k]] for k in ("db_image", "q_image")}
        locs = {k: np.asarray(fields[k], dtype=np.float64).reshape(len(fields[k]), -1) if fields[k] else np.zeros((0, 2))
                for k in ("db_loc", "q_loc")}
        radius = float(fields["radius"])
        if not all(np.isfinite(v).all() for v in locs.values()):
            raise ValueError("its positions hold non-finite numbers (NaN or infinity)")
    except (ValueError, KeyError, TypeError) as error:
        raise VPRBenchError(f"Cannot read {path}: {error}. Expected a MATLAB file with a NetVLAD 'dbStruct'; "
                            "replace it (re-download the dataset).") from None
    for split in ("db", "q"):
        if len(images[f"{split}_image"]) != len(locs[f"{split}_loc"]):
            raise VPRBenchError(f"{path}: {len(images[f'{split}_image'])} image names but {len(locs[f'{split}_loc'])} positions.")
    return {**images, **locs, "radius": radius}


def mat_expects(options: dict) -> list[str]:
    return [options.get("mat", "oxdatapart.mat"), options.get("images", "oxDataPart") + "/"]


@layout("netvlad-mat", expects=mat_expects)
def read_netvlad_mat(root: Path, manifest: DatasetManifest):
    opts = manifest.options
    mat = require(root, opts.get("mat", "oxdatapart.mat"), manifest, "file")
    db_struct = read_db_struct(mat)
    folder = require(root, opts.get("images", "oxDataPart"), manifest)
    database = [inside(folder, name, mat) for name in db_struct["db_image"]]
    queries = [inside(folder, name, mat) for name in db_struct["q_image"]]
    # an image named twice is counted twice, and a query among the database finds itself
    seen = {}
    for split, paths in (("database", database), ("queries", queries)):
        for path in paths:
            key = os.path.normpath(path)
            if key in seen:
                raise VPRBenchError(f"{mat} names {str(path.relative_to(folder))!r} twice (in the {seen[key]} and in the {split}); "
                                    "each image must be named once: fix or replace the file (re-download the dataset).")
            seen[key] = split
    missing = [p for p in database + queries if not p.is_file()]
    if missing:
        raise VPRBenchError(
            f"Dataset {manifest.name!r}: {len(missing)} image(s) named in {mat.name} "
            f"are missing under {folder}, e.g. {str(missing[0].relative_to(folder))!r}."
        )
    radius = manifest.radius if manifest.radius is not None else db_struct["radius"]
    ground_truth = GroundTruth(unit="metres", radius=radius, database_positions=db_struct["db_loc"], query_positions=db_struct["q_loc"])
    return from_manifest(manifest, root, database, queries, ground_truth)
