"""A stored record is served only for the computation it holds: what changes a run's numbers
without changing its spec's row (a default that follows K) keeps the record from being served."""
from __future__ import annotations

from vprbench.cli.main import main
from vprbench.evaluation import read_results
from vprbench.spec import resolve_spec
from runs import register_weighted_grey

PLAN = ('search = { index = "hnsw", options = { hnsw_m = 2 } }\n\n[[methods]]\nname = "hog"\n'
        'options = { resize = [32, 32] }\n\n[[datasets]]\nname = "corridor"\n')


def runs_of(plan, shared_data, cache, capsys):
    """A function running the plan at K 1 and returning the records the cache then holds."""
    def run() -> list[dict]:
        code = main([str(a) for a in ("run", plan, "--k", 1, "--quiet", "--data-dir", shared_data, "--cache-dir", cache)])
        assert code == 0, capsys.readouterr().err
        capsys.readouterr()
        return read_results(cache)
    return run


def test_a_sweep_does_not_serve_an_approximate_search_made_for_another_largest_k(shared_data, tmp_path, capsys):
    """The shortlist (and hnsw's ef_search) default to the largest K: a cell asking K 1 5 was skipped as
    complete with the record searched with a shortlist of 111 for K 1 5 111 (another Recall@5)."""
    plan, cache = tmp_path / "plan.toml", tmp_path / "cache"
    plan.write_text(PLAN)

    def run(*ks) -> list[dict]:
        code = main([str(a) for a in ("run", plan, "--k", *ks, "--quiet", "--data-dir", shared_data,
                                      "--cache-dir", cache)])
        assert code == 0, capsys.readouterr().err
        capsys.readouterr()
        return read_results(cache)

    [deep] = run(1, 5, 111)
    assert deep["search"]["options"]["shortlist"] == 111
    records = run(1, 5)
    assert len(records) == 2, "the K 1 5 cell was served the record searched for K 1 5 111"
    assert records[-1]["search"]["options"]["shortlist"] == records[-1]["search"]["options"]["ef_search"] == 100
    assert len(run(1, 5)) == 2  # its own record is found again
    assert len(run(1, 111)) == 2  # and the deep one serves a K its shortlist was made for


def test_a_sweep_does_not_serve_an_approximate_search_made_by_another_version_of_its_code(shared_data, tmp_path,
                                                                                           capsys, monkeypatch):
    """ivf-pq's lists came to be picked by vprbench, not faiss (other lists where two centroids tie): its spec
    and options stayed the same, so a sweep kept serving records of the old code. The search's version is now
    in its record, and a record of another version is not served."""
    from vprbench.search import approximate

    plan, cache = tmp_path / "plan.toml", tmp_path / "cache"
    plan.write_text(PLAN)
    run = runs_of(plan, shared_data, cache, capsys)

    [old] = run()
    version = approximate.VERSIONS["hnsw"]
    assert old["search"]["version"] == version
    assert len(run()) == 1  # found again while the code is the same
    monkeypatch.setitem(approximate.VERSIONS, "hnsw", version + 1)
    records = run()
    assert len(records) == 2, "the record of the old search code was served"
    assert records[-1]["search"]["version"] == version + 1
    assert len(run()) == 2  # the new record is found again


def test_a_sweep_does_not_serve_a_record_whose_descriptors_the_method_no_longer_computes(shared_data, tmp_path,
                                                                                       capsys, monkeypatch):
    """A method's fingerprint names what its descriptors depend on beyond its options (a version its author
    raises, OpenCV's major version): it changed, the stores were recomputed, but a sweep still served the
    record of the old descriptors (records are found by the spec's row, which holds only the options)."""
    from vprbench.methods.hog import HOG

    plan, cache = tmp_path / "plan.toml", tmp_path / "cache"
    plan.write_text('[[methods]]\nname = "hog"\noptions = { resize = [32, 32] }\n\n[[datasets]]\nname = "corridor"\n')
    run = runs_of(plan, shared_data, cache, capsys)

    [old] = run()
    fingerprint = HOG.fingerprint
    monkeypatch.setattr(HOG, "fingerprint", lambda self: {**fingerprint(self), "version": 2})
    records = run()
    assert len(records) == 2, "the record of the old descriptors was served"
    assert records[-1]["method_fingerprint"]["version"] == 2 and "version" not in old["method_fingerprint"]
    assert records[-1]["descriptors_computed"] == {"database": 111, "queries": 111}
    assert len(run()) == 2  # the new record is found again


def test_a_stage_weights_folder_is_known_by_its_files(tmp_path):
    """patch-mnn takes a folder holding the release's file as its weights: the spec kept the folder's path,
    so a file replaced in it was the same run (a sweep served the record of the old weights)."""
    from vprbench.spec import resolve_spec

    folder = tmp_path / "weights"
    folder.mkdir()
    weights = folder / "dinov2_vits14_pretrain.pth"

    def spec():
        stage = {"name": "patch-mnn", "backbone": "dinov2_vits14", "weights": str(folder), "k": 20}
        return resolve_spec("hog", "corridor", options={"resize": [32, 32]}, stages=[stage], ks=(1, 5))

    weights.write_bytes(b"first weights")
    before = spec()
    assert before.stages[0].files["weights"].startswith("folder:")
    weights.write_bytes(b"other weights, replaced in place")
    replaced = spec()
    assert replaced.key != before.key and replaced.row_key != before.row_key
    (folder / ".DS_Store").write_bytes(b"x")  # a hidden file is none of its files
    assert spec().key == replaced.key


def test_a_sweep_does_not_serve_a_record_whose_pca_another_memory_budget_fitted(shared_data, tmp_path, capsys,
                                                                              monkeypatch):
    """--search-memory picks PCA-whitening's solver (exact, or randomized when the exact one does not
    fit), which no spec names: a sweep with a budget for the exact fit was served the randomized one's
    record. On Corridor (111 database images) the search itself needs more than the exact fit (12.7 MB
    against 0.1 MB), so the exact fit is made dearer here, as a database of thousands of images makes it."""
    from vprbench.aggregation import pca

    solver_memory = pca._solver_memory
    monkeypatch.setattr(pca, "_solver_memory", lambda solver, n, d, dim: solver_memory(solver, n, d, dim)
                        + (50_000_000 if solver != "randomized" else 0))
    plan, cache = tmp_path / "plan.toml", tmp_path / "cache"
    plan.write_text('[[methods]]\nname = "anyloc"\noptions = { backbone = "dinov2_vits14", weights = "random", '
                    'layer = 1, aggregation = "gem", resize = [28, 28], pca_dim = 16 }\n\n'
                    '[[datasets]]\nname = "corridor"\n')

    def run(*memory) -> list[dict]:
        code = main([str(a) for a in ("run", plan, "--k", 1, *memory, "--quiet", "--data-dir", shared_data,
                                      "--cache-dir", cache)])
        assert code == 0, capsys.readouterr().err
        capsys.readouterr()
        return read_results(cache)

    def solver(record) -> str:
        return record["search"]["postprocess"]["key"]["postprocessor"]["solver"]

    [randomized] = run("--search-memory", "20MB")
    assert solver(randomized) == "randomized"
    records = run()
    assert len(records) == 2, "the record of the randomized fit was served to a run that fits the exact one"
    assert solver(records[-1]) == "gram" and records[-1]["descriptors_computed"] == {"database": 0, "queries": 0}
    assert len(run()) == len(run("--search-memory", "20MB")) == 2  # each budget finds its own record again
    # the fitted states, keyed by the solver too, lie side by side
    assert len({r["search"]["postprocess"]["file"] for r in records}) == 2


def test_a_sweep_does_not_serve_a_record_a_stage_no_longer_computes(shared_data, tmp_path, capsys, monkeypatch):
    """A stage's code is in no spec: a re-ranker changed, its author raising the version in its fingerprint,
    but a sweep still served the records it re-ranked before. Records without a stage fingerprint (written
    before stages had one) still count as made with the default one."""

    from vprbench.stages.expansion import AlphaQE

    plan, cache = tmp_path / "plan.toml", tmp_path / "cache"
    plan.write_text('[[methods]]\nname = "hog"\noptions = { resize = [32, 32] }\n\n[[datasets]]\nname = "corridor"\n')

    def run() -> list[dict]:
        code = main([str(a) for a in ("run", plan, "--k", 1, "--rerank", "aqe", "--quiet", "--data-dir",
                                      shared_data, "--cache-dir", cache)])
        assert code == 0, capsys.readouterr().err
        capsys.readouterr()
        return read_results(cache)

    monkeypatch.setattr(AlphaQE, "fingerprint", lambda self: {})  # a stage with the default fingerprint
    [old] = run()
    assert "fingerprint" not in old["stages"][0]  # the default is not written: old records look the same
    assert len(run()) == 1
    monkeypatch.setattr(AlphaQE, "fingerprint", lambda self: {"version": 3})
    records = run()
    assert len(records) == 2, "the record of the stage's old code was served"
    assert records[-1]["stages"][0]["fingerprint"] == {"version": 3}
    assert len(run()) == 2  # the new record is found again
    monkeypatch.setattr(AlphaQE, "fingerprint", lambda self: {})
    assert len(run()) == 2  # and the old code's record (no fingerprint in it) for the default again


def test_an_approximate_search_as_deep_as_its_largest_k_is_a_row_of_its_own(shared_data, tmp_path):
    """hnsw's unset shortlist (and ef_search) follow the largest K: K 1 5 searched a shortlist of 100, K 1 5 111
    one of 111, yet both runs had one leaderboard row, whose cells showed either search's Recall@1."""
    from vprbench.evaluation import evaluate
    from vprbench.spec import RunSettings, RunSpec

    settings = RunSettings(data_dir=shared_data, cache_dir=tmp_path)
    records = [evaluate(resolve_spec("hog", "corridor", options={"resize": [32, 32]}, search="hnsw", ks=ks,
                                     data_dir=shared_data), settings) for ks in ((1, 5), (1, 5, 111))]
    searched = [r["search"]["options"]["shortlist"] for r in records]
    rows = {RunSpec.model_validate(r["spec"]).row_key for r in records}
    assert searched == [100, 111] and len(rows) == 2, "two searches shown in one leaderboard row"
    # what is written is what ran: the spec read back searches as its record did
    assert RunSpec.model_validate(records[1]["spec"]).search.options == {"shortlist": 111}
    shallow = resolve_spec("hog", "corridor", search="hnsw", stages=[{"name": "aqe", "k": 100}], ks=(1,))
    assert shallow.search.options == {}  # a run within the default shortlist keeps its identity


def test_a_file_an_option_names_keys_the_store_by_its_bytes(shared_data, tmp_path, scratch_methods):
    """The spec names a file by its bytes, the store named it by its path: the file edited in place, the
    run was another (its own key, the new sha256 in its record) but read the descriptors of the old bytes."""
    import numpy as np

    from vprbench.evaluation import evaluate
    from vprbench.spec import RunSettings

    register_weighted_grey(scratch_methods)  # a plugin whose fingerprint() forgets its file: the store key still sees it
    table, run = tmp_path / "table.npy", RunSettings(data_dir=shared_data, cache_dir=tmp_path / "cache")
    records = []
    for content in (np.ones(16), np.arange(1.0, 17.0)):
        np.save(table, content)
        spec = resolve_spec("weighted-grey", "corridor", options={"table": str(table)}, ks=[1], data_dir=shared_data)
        records.append(evaluate(spec, run))
    assert records[0]["spec"]["files"] != records[1]["spec"]["files"]
    assert records[1]["descriptors_computed"] == {"database": 111, "queries": 111}, "the old bytes' store was read"
    assert records[0]["context"]["store"] != records[1]["context"]["store"]
