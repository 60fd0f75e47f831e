"""PCA-whitening fitted on a domain's databases stacked (AnyLoc's pca_on = "domain", as the authors'
scripts/joint_pca_project.py): the stacked rows, the run that describes the other databases, and what
it refuses."""
from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest

from vprbench.aggregation.pca import PCAWhitening
from vprbench.errors import VPRBenchError
from vprbench.evaluation.joint import JointRows
from vprbench.evaluation.results import read_results
from vprbench.row_sources import ArrayRows

#: the urban domain's databases: Oxford, St Lucia, Pitts-30k (the largest stack a joint PCA serves)
URBAN = (213, 1549, 10000)


def test_joint_rows_read_as_the_stacked_matrix_at_the_urban_domains_size():
    rng = np.random.default_rng(0)
    arrays = [rng.standard_normal((n, 32)).astype(np.float32) + i for i, n in enumerate(URBAN)]
    joint, stacked = JointRows([ArrayRows(a) for a in arrays]), np.concatenate(arrays)
    assert (joint.row_count, joint.dim) == (11762, 32)
    for start, stop in ((0, 11762), (200, 1800), (212, 214), (1761, 1763), (5000, 5001), (213, 1762), (0, 213),
                        (11761, 11762), (11762, 11762)):
        np.testing.assert_array_equal(joint.read_rows(start, stop), stacked[start:stop])
    picked = np.sort(rng.choice(11762, 500, replace=False))
    np.testing.assert_array_equal(joint.read_rows_at(picked), stacked[picked])
    # the fit streams the stack chunk by chunk: as on the matrix, within float32 rounding of the sums
    fitted, reference = PCAWhitening(16).fit(joint), PCAWhitening(16).fit(stacked)
    np.testing.assert_allclose(fitted.mean, reference.mean, atol=1e-5)
    np.testing.assert_allclose(fitted.projection, reference.projection, rtol=1e-4, atol=1e-5)
    assert joint.folder is None  # parts of unknown content: no state is kept for them


class _Part(ArrayRows):
    def __init__(self, array, key, folder):
        super().__init__(array, folder)
        self.key = key

    def content_key(self):
        return self.key


def test_joint_rows_are_keyed_by_every_part_and_refuse_mixed_widths(tmp_path):
    rows = np.ones((3, 4), np.float32)
    one = JointRows([_Part(rows, "a", tmp_path / "first"), _Part(rows, "b", tmp_path / "second")])
    other = JointRows([_Part(rows, "a", tmp_path / "first"), _Part(rows, "c", tmp_path / "second")])
    assert one.folder == tmp_path / "first" and one.content_key() != other.content_key()
    with pytest.raises(VPRBenchError, match="must share their dimension and dtype, got 4 x float32, 5 x float32"):
        JointRows([ArrayRows(rows), ArrayRows(np.ones((3, 5), np.float32))])


def test_the_domain_is_the_evaluated_datasets_vocabulary_domain():
    from vprbench.methods.anyloc_options import pca_datasets

    assert pca_datasets("domain", "gardens-point") == ("indoor", ["gardens-point", "17places", "baidu-mall"])
    assert pca_datasets("domain", "pitts30k") == ("urban", ["oxford", "st-lucia", "pitts30k"])
    assert pca_datasets("domain", "mid-atlantic-ridge") == ("underwater", ["mid-atlantic-ridge"])
    assert pca_datasets("database", "pitts30k") is None
    with pytest.raises(VPRBenchError, match="dataset 'corridor' is in no domain .* use pca_on=database"):
        pca_datasets("domain", "corridor")


class _Stacks:
    """A method whose post-processor is fitted on the databases `names` (a plugin's postprocess_datasets)."""

    name, needs_fit = "stacks", False

    def __init__(self, names):
        self.names = names

    def postprocess_datasets(self):
        return self.names


@pytest.mark.parametrize("names", [["17places"], ["gardens-point", "gardens-point"], "gardens-point", [1]])
def test_a_methods_stack_names_distinct_benchmarks_the_evaluated_one_among_them(names):
    from types import SimpleNamespace

    from vprbench.evaluation.joint import joint_members

    evaluated = SimpleNamespace(name="gardens-point")
    with pytest.raises(VPRBenchError, match=r"Method 'stacks': postprocess_datasets\(\) must return distinct "
                                            r"benchmark names among them the evaluated 'gardens-point', got "):
        joint_members(_Stacks(names), evaluated, None, None)
    assert joint_members(_Stacks(["gardens-point"]), evaluated, None, None) is None  # its own database: no stack
    assert joint_members(_Stacks(None), evaluated, None, None) is None


class _Unfitted(_Stacks):
    """A plugin that names a stack but fits nothing on it: no postprocessor(), or not compared by cosine."""

    compare = "cosine"

    def postprocessor(self):
        return None


@pytest.mark.parametrize("compare", ["cosine", "l2"])
def test_a_stack_is_refused_for_a_method_that_fits_no_post_processor_on_it(compare):
    """Before: every database of the stack was described and the record named them, for a fit never made."""
    from types import SimpleNamespace

    from vprbench.aggregation.pca import PCAWhitening
    from vprbench.evaluation.joint import joint_members

    method = _Unfitted(["gardens-point", "17places"])
    method.compare = compare
    if compare != "cosine":
        method.postprocessor = lambda: PCAWhitening(8)
    with pytest.raises(VPRBenchError, match=r"Method 'stacks': postprocess_datasets\(\) names gardens-point, 17places "
                                            r"to fit its postprocessor\(\) on, but "):
        joint_members(method, SimpleNamespace(name="gardens-point"), None, None)


# ---------------------------------------------------------------- runs on two small benchmarks
def _benchmark(folder: Path, count: int, rng) -> None:
    """A VPR-Bench layout (ref/, query/, ground_truth_new.npy) of `count` random 42 x 42 images per split."""
    from PIL import Image

    for split in ("ref", "query"):
        (folder / split).mkdir(parents=True)
        for i in range(count):
            Image.fromarray(rng.integers(0, 255, (42, 42, 3), dtype=np.uint8)).save(folder / split / f"{i:07d}.jpg")
    rows = np.empty((count, 2), dtype=object)
    for i in range(count):
        rows[i, 0], rows[i, 1] = i, [i]
    np.save(folder / "ground_truth_new.npy", rows, allow_pickle=True)


@pytest.fixture(scope="module")
def indoor_data(tmp_path_factory) -> Path:
    """Gardens Point (200) and 17 Places (406) at their manifests' counts and folders."""
    root, rng = tmp_path_factory.mktemp("data"), np.random.default_rng(0)
    _benchmark(root / "gardens", 200, rng)
    _benchmark(root / "17places", 406, rng)
    return root


@pytest.fixture
def two_dataset_indoor(monkeypatch):
    """The indoor domain as Gardens Point and 17 Places (Baidu Mall's layout is not built here)."""
    from vprbench.methods import anyloc_options, anyloc_vocabulary

    policies = dict(anyloc_vocabulary.vocabulary_policies())
    policies["domains"] = {**policies["domains"], "indoor": [["gardens-point", 1], ["17places", 1]]}
    monkeypatch.setattr(anyloc_vocabulary, "vocabulary_policies", lambda: policies)
    monkeypatch.setattr(anyloc_options, "vocabulary_policies", lambda: policies)


MODEL = ("--method", "anyloc", "--backbone", "dinov2_vits14", "--weights", "random", "--layer", "0", "--resize", "42", "42")
SMALL = (*MODEL, "--aggregation", "gem", "--pca-dim", "8")


def _database(cache: Path, record: dict, dataset: str) -> np.ndarray:
    folder = record["context"]["store"]["folders"]["database"] if record["dataset"] == dataset else None
    pattern = folder or f"*/{dataset}-database-*"
    (path,) = (cache / "stores").glob(f"{pattern}/database.h5")
    with h5py.File(path, "r") as f:
        return f["descriptors"][...].astype(np.float64)


def test_a_run_fits_on_the_domains_databases_stacked_and_the_next_reuses_them(cli, indoor_data, two_dataset_indoor, tmp_path):
    where = ("--data-dir", indoor_data, "--cache-dir", tmp_path / "cache")
    code, out, err = cli("evaluate", *SMALL, "--pca-on", "domain", "--dataset", "gardens-point", *where, "--json")
    assert code == 0, err
    record = json.loads(out)
    stack = record["context"]["postprocess_datasets"]
    assert {name: {k: v for k, v in found.items() if k != "images"} for name, found in stack.items()} == {
        "gardens-point": {"protocol": "gardens-point:anyloc", "database_images": 200, "computed": 200},
        "17places": {"protocol": "17places:anyloc", "database_images": 406, "computed": 406}}
    assert stack["gardens-point"]["images"] == record["dataset_fingerprints"]["images"]
    assert record["provenance"]["pca"]["datasets"] == ["gardens-point", "17places"]
    assert 0 < record["timings"]["stack_s"] < record["timings"]["total_s"]  # describing 17 Places' database
    post = record["search"]["postprocess"]
    assert post["state"] == "fitted" and post["key"]["rows"]["count"] == 606
    # the state is fitted on both databases: its mean is the stack's, not Gardens Point's alone
    stacked = np.concatenate([_database(tmp_path / "cache", record, "gardens-point"),
                              _database(tmp_path / "cache", record, "17places")])
    with np.load(post["file"]) as state:
        mean = state["pca_mean"].astype(np.float64)
    scale = np.abs(stacked).max()
    assert np.abs(mean - stacked.mean(axis=0)).max() <= 1e-5 * scale
    assert np.abs(mean - stacked[:200].mean(axis=0)).max() > 1e-3 * scale

    # 17 Places' run finds its database described and the stack's PCA fitted
    code, out, err = cli("evaluate", *SMALL, "--pca-on", "domain", "--dataset", "17places", *where, "--json")
    assert code == 0, err
    places = json.loads(out)
    assert places["context"]["postprocess_datasets"]["17places"]["computed"] == 0
    assert stack["17places"]["images"] == places["dataset_fingerprints"]["images"]  # the content each was read with
    assert places["descriptors_computed"]["database"] == 0 and places["descriptors_computed"]["queries"] == 406
    assert places["search"]["postprocess"]["state"] == "loaded" and places["search"]["postprocess"]["file"] == post["file"]

    # fitted on the evaluated database alone, another run (its own key and rows)
    code, out, err = cli("evaluate", *SMALL, "--dataset", "gardens-point", *where, "--json")
    alone = json.loads(out)
    assert code == 0 and alone["search"]["postprocess"]["key"]["rows"]["count"] == 200
    assert alone["spec_key"] != record["spec_key"] and "postprocess_datasets" not in alone["context"]


def _refused(cli, *args) -> str:
    code, out, err = cli(*args)
    assert code == 1 and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    return err


def test_what_a_joint_fit_refuses(cli, indoor_data, two_dataset_indoor, tmp_path, shared_data):
    cache = tmp_path / "cache"
    # a member dataset missing: named, with why it is read and how to get it, before any image is described
    lonely = tmp_path / "lonely"
    lonely.mkdir()
    (lonely / "gardens").symlink_to(indoor_data / "gardens")
    err = _refused(cli, "evaluate", *SMALL, "--pca-on", "domain", "--dataset", "gardens-point", "--data-dir", lonely,
                   "--cache-dir", cache)
    assert "fits its post-processor on the databases of gardens-point, 17places stacked, so evaluating " \
           "gardens-point needs 17places: Dataset '17places' is not in the data root" in err
    # VLAD with a vocabulary fitted on each dataset's own database: descriptors that cannot be stacked
    err = _refused(cli, "evaluate", *MODEL, "--pca-dim", "8", "--clusters", "2", "--vocabulary", "map",
                   "--pca-on", "domain", "--dataset", "gardens-point", "--data-dir", indoor_data, "--cache-dir", cache)
    assert "it would fit a vocabulary on gardens-point's own database" in err and "not be comparable" in err
    assert not (cache / "stores").exists()
    # a memory budget too small for the stack's fit and the search: said once, in one line naming the most that
    # any part of the run needs, once the evaluated dataset is described, before the others
    err = _refused(cli, "evaluate", *SMALL, "--pca-on", "domain", "--dataset", "gardens-point", "--data-dir",
                   indoor_data, "--cache-dir", cache, "--search-memory", "20kB")
    assert "A memory budget of 20.0 kB is too small for this run: retrieval's exact search needs the most " \
           "(the PCAWhitening fit " in err
    assert len(list((cache / "stores").glob("*/gardens-point-database-*/database.h5"))) == 1
    assert not list((cache / "stores").glob("*/17places-database-*"))
    # a dataset in no domain
    err = _refused(cli, "evaluate", *SMALL, "--pca-on", "domain", "--dataset", "corridor", "--data-dir", shared_data,
                   "--cache-dir", cache)
    assert "dataset 'corridor' is in no domain" in err
    # describe fits on --fit-on: it refuses to stack
    image = indoor_data / "gardens" / "query" / "0000001.jpg"
    err = _refused(cli, "describe", *SMALL, "--pca-on", "domain", "--dataset", "gardens-point", "--data-dir",
                   indoor_data, "--cache-dir", cache, image, "--out", tmp_path / "x.npy")
    assert "as `vprbench evaluate --dataset gardens-point` does; describe fits it on --fit-on" in err
    assert not (tmp_path / "x.npy").exists()
    # a value it does not know, and the option without PCA
    assert "option pca_on takes one of database, domain; got 'domian'" in _refused(
        cli, "evaluate", *SMALL, "--pca-on", "domian", "--dataset", "corridor", "--data-dir", shared_data)
    assert "pca_on='domain' is not used here (only PCA-whitening uses it, pca_dim is unset)" in _refused(
        cli, "evaluate", *MODEL, "--aggregation", "gem", "--pca-on", "domain", "--dataset", "corridor", "--data-dir", shared_data)


DRIVER = """import sys
from vprbench.methods import anyloc_options, anyloc_vocabulary
policies = dict(anyloc_vocabulary.vocabulary_policies())
policies["domains"] = {**policies["domains"], "indoor": [["gardens-point", 1], ["17places", 1]]}
anyloc_vocabulary.vocabulary_policies = anyloc_options.vocabulary_policies = lambda: policies
from vprbench.cli.main import main
sys.exit(main(sys.argv[1:]))
"""


def test_two_torchrun_ranks_describe_every_database_of_the_stack_as_one_process(cli, indoor_data, two_dataset_indoor,
                                                                                 tmp_path):
    import os
    import subprocess
    import sys

    driver = tmp_path / "driver.py"
    driver.write_text(DRIVER)
    args = ["evaluate", *SMALL, "--pca-on", "domain", "--dataset", "gardens-point", "--data-dir", str(indoor_data),
            "--json"]
    done = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node=2",
                           str(driver), *args, "--cache-dir", str(tmp_path / "ranks")], capture_output=True, text=True,
                          timeout=600, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert done.returncode == 0, done.stderr[-3000:]
    ranks = json.loads(done.stdout)
    code, out, err = cli(*args, "--cache-dir", tmp_path / "one")
    assert code == 0, err
    one = json.loads(out)
    assert ranks["context"]["distributed"]["computed_per_rank"] == [{"database": 100, "queries": 100},
                                                                    {"database": 100, "queries": 100}]
    assert ranks["context"]["postprocess_datasets"] == one["context"]["postprocess_datasets"]
    # the stacked rows' content key is a hash of every row's checksum: the same rows, bit for bit
    assert ranks["search"]["postprocess"]["key"] == one["search"]["postprocess"]["key"]
    # the fit's float sums may differ in the last bit between thread counts (OMP 1 here, the default in process):
    # at most one of the 200 queries changes its rank-K answer
    assert all(abs(ranks["recall"][k] - one["recall"][k]) <= 100 / 200 for k in one["recall"])


def test_two_datasets_of_a_stack_evaluated_at_once_share_its_stores_and_fit(indoor_data, tmp_path, cli, two_dataset_indoor):
    """Each run describes the other's database: they meet at the store folders' locks and at the fit's file."""
    import subprocess
    import sys

    driver = tmp_path / "driver.py"
    driver.write_text(DRIVER)
    runs = {name: subprocess.Popen(
        [sys.executable, str(driver), "evaluate", *SMALL, "--pca-on", "domain", "--dataset", name, "--data-dir",
         str(indoor_data), "--cache-dir", str(tmp_path / "cache"), "--json"], stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True) for name in ("gardens-point", "17places")}
    records = {}
    for name, run in runs.items():
        out, err = run.communicate(timeout=600)
        assert run.returncode == 0, err[-3000:]
        records[name] = json.loads(out)
    posts = [r["search"]["postprocess"] for r in records.values()]
    assert posts[0]["file"] == posts[1]["file"] and posts[0]["key"] == posts[1]["key"]
    assert len(list((tmp_path / "cache" / "stores").glob("*/*/postprocess-*.npz"))) == 1
    assert len(list((tmp_path / "cache" / "stores").glob("*/*/*.h5"))) == 4  # two databases, two query sets
    # what each described, the other did not: every database image was described once
    described = sum(r["context"]["postprocess_datasets"][other]["computed"] + r["descriptors_computed"]["database"]
                    for (name, r), other in zip(records.items(), ("17places", "gardens-point")))
    assert described == 606
    # served again, one at a time, from what the two left: the same results
    for name, record in records.items():
        code, out, err = cli("evaluate", *SMALL, "--pca-on", "domain", "--dataset", name, "--data-dir", indoor_data,
                             "--cache-dir", tmp_path / "cache", "--json")
        assert code == 0, err
        again = json.loads(out)
        assert again["recall"] == record["recall"] and sum(again["descriptors_computed"].values()) == 0


PLAN = """name = "joint"
k = [1, 5]

[[methods]]
name = "anyloc"
[methods.options]
backbone = "dinov2_vits14"
weights = "random"
layer = 0
resize = [42, 42]
aggregation = "gem"
pca_dim = 8
pca_on = "{pca_on}"

[[datasets]]
name = "gardens-point"
"""


def test_a_sweep_runs_a_stacked_cell_again_once_another_database_of_its_stack_changed(cli, indoor_data,
                                                                                      two_dataset_indoor, tmp_path):
    """The cell's stored record was fitted on 17 Places' database as it was: edited, the fit is not that one."""
    import shutil

    from PIL import Image

    data, cache, plan = tmp_path / "data", tmp_path / "cache", tmp_path / "plan.toml"
    shutil.copytree(indoor_data, data)
    plan.write_text(PLAN.format(pca_on="domain"))
    sweep = ("run", plan, "--data-dir", data, "--cache-dir", cache)
    code, out, err = cli(*sweep)
    assert code == 0, out + err
    assert "1 skipped" in cli(*sweep)[1]  # nothing changed: served
    rng = np.random.default_rng(1)
    for i in range(0, 406, 2):
        image = Image.fromarray(rng.integers(0, 255, (42, 42, 3), dtype=np.uint8))
        image.save(data / "17places" / "ref" / f"{i:07d}.jpg")
    code, out, err = cli(*sweep)
    assert code == 0 and "1 ran" in out, out
    code, out, err = cli("evaluate", *SMALL, "--pca-on", "domain", "--dataset", "gardens-point", "--k", 1, 5,
                         "--data-dir", data, "--cache-dir", tmp_path / "fresh", "--json")
    assert code == 0, err
    fresh = json.loads(out)
    (record,) = [r for r in read_results(cache) if r["created"] == max(r["created"] for r in read_results(cache))]
    assert record["search"]["postprocess"]["key"] == fresh["search"]["postprocess"]["key"]
    assert record["recall"] == fresh["recall"]


def test_candidates_exported_with_the_stack_refuse_a_run_fitted_on_its_own_database_naming_pca_on(
        cli, indoor_data, two_dataset_indoor, tmp_path):
    """Before: the file's options were cut after four ('pca_dim': 8,...), so the one that differs was not named."""
    where = ("--data-dir", indoor_data, "--cache-dir", tmp_path / "cache")
    code, out, err = cli("candidates", "export", *SMALL, "--pca-on", "domain", "--dataset", "gardens-point", "--k", 20,
                         "--out", tmp_path / "top.h5", *where)
    assert code == 0, err
    rerank = ("--rerank", "aqe", "--rerank-k", 20, "--candidates", tmp_path / "top.h5", *where)
    code, out, err = cli("evaluate", *SMALL, "--pca-on", "domain", "--dataset", "gardens-point", *rerank, "--json")
    assert code == 0, err
    record = json.loads(out)
    assert record["context"]["postprocess_datasets"]["17places"]["computed"] == 0  # described by the export
    assert record["provenance"]["pca"]["datasets"] == ["gardens-point", "17places"]
    assert 0 < record["timings"]["stack_s"] < record["timings"]["total_s"]  # describing 17 Places' database
    err = _refused(cli, "evaluate", *SMALL, "--dataset", "gardens-point", *rerank)
    assert "was exported by another retriever" in err and "options that differ: pca_on 'domain' in the file, " \
           "unset in this run" in err
