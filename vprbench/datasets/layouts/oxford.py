"""`netvlad-mat`: a NetVLAD-style dbStruct .mat naming database/query images and their positions.

The AnyLoc release of the Oxford RobotCar subsample (`Oxford_Robotcar/oxdatapart.mat` with
images under `oxDataPart/`) uses it: a cell array holding, in order, dbImage, locDb, qImage,
locQ, numDb, numQ, posDistThr, posDistSqThr. Image names have their spaces removed, as the
authors' loader does. NetVLAD's own files (e.g. `datasets/pitts30k_test.mat`: a struct with
named fields dbImageFns, utmDb, qImageFns, utmQ, posDistThr) are read by field name.
The manifest's radius (the paper's) wins over posDistThr.

Options: `mat` (file), `images` (folder the names are relative to).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ...errors import VPRBenchError
from ..manifest import DatasetManifest
from ..model import GroundTruth
from . import from_manifest, layout, require


def read_db_struct(path: Path) -> dict:
    from scipy.io import loadmat

    try:
        loaded = loadmat(path)["dbStruct"]
        names = ("db_image", "db_loc", "q_image", "q_loc", "num_db", "num_q", "radius")
        if loaded.dtype.names and "dbImageFns" in loaded.dtype.names:  # NetVLAD's named struct
            record = loaded.ravel()[0]
            fields = {k: record[n] for k, n in zip(names, ("dbImageFns", "utmDb", "qImageFns", "utmQ", "numImages", "numQueries", "posDistThr"))}
        else:  # a 1x8 cell array (as the release has it) or a struct: fields by position
            values = list(loaded.ravel()[0]) if loaded.dtype.names else list(loaded.ravel())
            if len(values) < len(names):
                raise ValueError(f"dbStruct has {len(values)} fields, expected at least {len(names)}")
            fields = dict(zip(names, values))
        images = {k: [str(np.ravel(v)[0]).replace(" ", "") for v in np.ravel(fields[k])] for k in ("db_image", "q_image")}
        locs = {k: np.asarray(fields[k], dtype=np.float64) for k in ("db_loc", "q_loc")}
        # NetVLAD stores locations as 2xN
        locs = {k: v.T if v.shape[0] == 2 and v.shape[1] != 2 else v for k, v in locs.items()}
        radius = float(np.ravel(fields["radius"])[0])
    except (OSError, ValueError, KeyError, IndexError, TypeError, NotImplementedError) as error:
        raise VPRBenchError(f"Cannot read {path}: {error}. Expected a MATLAB file with a NetVLAD 'dbStruct'.") from None
    for split in ("db", "q"):
        if len(images[f"{split}_image"]) != len(locs[f"{split}_loc"]):
            raise VPRBenchError(f"{path}: {len(images[f'{split}_image'])} image names but {len(locs[f'{split}_loc'])} positions.")
    return {**images, **locs, "radius": radius}


def mat_expects(options: dict) -> list[str]:
    return [options.get("mat", "oxdatapart.mat"), options.get("images", "oxDataPart") + "/"]


@layout("netvlad-mat", expects=mat_expects)
def read_netvlad_mat(root: Path, manifest: DatasetManifest):
    opts = manifest.options
    struct = read_db_struct(require(root, opts.get("mat", "oxdatapart.mat"), manifest, "file"))
    folder = require(root, opts.get("images", "oxDataPart"), manifest)
    database = [folder / name for name in struct["db_image"]]
    queries = [folder / name for name in struct["q_image"]]
    missing = [p for p in database + queries if not p.is_file()]
    if missing:
        raise VPRBenchError(
            f"Dataset {manifest.name!r}: {len(missing)} image(s) named in {opts.get('mat', 'oxdatapart.mat')} "
            f"are missing under {folder}, e.g. {missing[0].relative_to(folder)}."
        )
    radius = manifest.radius if manifest.radius is not None else struct["radius"]
    ground_truth = GroundTruth(unit="metres", radius=radius, database_positions=struct["db_loc"], query_positions=struct["q_loc"])
    return from_manifest(manifest, root, database, queries, ground_truth)
