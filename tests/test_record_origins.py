"""What software computed a record: the versions of the libraries that decide its numbers, and the
distribution (and version) that provides its method and each stage, shown on the dataset page."""
import json
import sys
from importlib import metadata

import numpy as np

from vprbench.evaluation import read_results


def test_a_real_run_records_the_libraries_and_the_distributions_it_ran(cli, shared_data):
    code, out, err = cli("evaluate", "--method", "hog", "--dataset", "corridor", "--data-dir", shared_data,
                         "--resize", 64, 64, "--rerank", "aqe", "--json")
    assert code == 0, err
    record = json.loads(out)
    versions = record["versions"]
    assert versions["opencv"] == metadata.version(metadata.packages_distributions()["cv2"][0])  # HOG is OpenCV's
    assert versions["scikit-learn"] == metadata.version("scikit-learn")  # AUC-PR is sklearn's
    assert versions["pillow"] == metadata.version("pillow")  # decodes every image
    core = {"module": "vprbench", "distribution": "vprbench", "version": metadata.version("vprbench")}
    assert record["origins"] == {"method": {"name": "hog", **core}, "stages": [{"name": "aqe", **core}]}
    [stored] = read_results()
    assert stored["origins"] == record["origins"] and stored["versions"] == versions


def test_a_method_registered_from_a_script_is_recorded_without_a_distribution(scratch_methods, shared_data):
    from runs import evaluate_method

    from vprbench import register_method
    from vprbench.datasets import load_dataset
    from vprbench.methods import Method, create_method

    class Scripted(Method):
        def describe(self, images):
            return np.eye(len(images), 8, dtype=np.float32)

    Scripted.__module__ = "__main__"  # as a class defined in a script or a notebook cell is
    register_method("scripted", Scripted)
    record = evaluate_method(create_method("scripted"), load_dataset("corridor", shared_data), ks=(1,))
    assert record["origins"]["method"] == {"name": "scripted", "module": "__main__", "distribution": None,
                                           "version": None}


def test_a_library_the_process_did_not_import_is_left_out(monkeypatch):
    # the versions are read from what this process imported: an installed library it never imported is absent
    # (was checked only against sys.modules itself, after a run in this very process: it could not fail)
    from vprbench.evaluation.provenance import _library_versions

    import scipy  # noqa: F401

    for module in ("timm", "torchvision", "kornia"):
        monkeypatch.delitem(sys.modules, module, raising=False)
    found = _library_versions()
    assert not {"timm", "torchvision", "kornia"} & set(found)
    assert found["scipy"] == metadata.version("scipy")
