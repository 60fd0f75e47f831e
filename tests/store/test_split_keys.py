"""Each split's store is keyed by the method and that split's own images (and, for a method that
fits, the database images its fit depends on): editing a query recomputes only the queries.
Was: one folder keyed by both splits, so one edited query recomputed the whole database."""
from __future__ import annotations

import shutil

import h5py
import pytest

import vprbench
from vprbench.datasets import load_dataset
from vprbench.evaluation import read_results

from runs import evaluate_method as evaluate
from vprbench.store import run_store

SOURCES = {**{f"database/d{i}.jpg": f"ref/{i:07d}.jpg" for i in range(6)},
           **{f"queries/q{i}.jpg": f"query/{i:07d}.jpg" for i in range(4)}}
HOG = ["--method", "hog", "--resize", 32, 32, "--k", 1, 3]


@pytest.fixture
def own(shared_data, tmp_path):
    """Six Corridor map images and four queries (each near the map image of its number)."""
    root = tmp_path / "own"
    for name, source in SOURCES.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(shared_data / "corridor" / source, root / name)
    (root / "positions.csv").write_text("image,x,y\n" + "".join(
        f"{name},{10 * int(name[-5])},0\n" for name in SOURCES))
    return root


def swap(root, name, source, shared_data):
    shutil.copy(shared_data / "corridor" / source, root / name)


def test_an_edited_query_recomputes_only_the_queries(own, shared_data, tmp_path, cli):
    cache = tmp_path / "cache"
    assert cli("evaluate", *HOG, "--dataset", own, "--cache-dir", cache)[0] == 0
    swap(own, "queries/q2.jpg", "query/0000005.jpg", shared_data)  # a retaken query
    assert cli("evaluate", *HOG, "--dataset", own, "--cache-dir", cache)[0] == 0
    first, second = read_results(cache)[-2:]
    assert second["descriptors_computed"] == {"database": 0, "queries": 4}
    assert cli("evaluate", *HOG, "--dataset", own, "--cache-dir", tmp_path / "scratch")[0] == 0
    scratch = read_results(tmp_path / "scratch")[-1]
    assert scratch["descriptors_computed"] == {"database": 6, "queries": 4}
    assert second["recall"] == scratch["recall"] and second["top_predictions"] == scratch["top_predictions"]
    assert second["top_predictions"] != first["top_predictions"]  # the edit really changed the queries
    # both records find their own stores: the database's shared, the queries' each their own
    db_first, db_second = run_store(first, "database", cache), run_store(second, "database", cache)
    assert db_first.path == db_second.path and db_second.row_count == 6
    assert run_store(first, "queries", cache).path != run_store(second, "queries", cache).path

    # an edited map image: the database is recomputed, the queries are not
    swap(own, "database/d1.jpg", "ref/0000009.jpg", shared_data)
    assert cli("evaluate", *HOG, "--dataset", own, "--cache-dir", cache)[0] == 0
    assert read_results(cache)[-1]["descriptors_computed"] == {"database": 6, "queries": 0}


def test_a_fit_follows_the_database_images(own, shared_data, tmp_path):
    """A fitted method's queries depend on the database through the fit: an edited query reuses
    the saved fit; an edited map image refits and recomputes both splits (no old fit reused)."""
    cache = tmp_path / "cache"

    def run():
        method = vprbench.create_method("fitted-test")
        return evaluate(method, load_dataset(str(own)), ks=[1, 3], cache_dir=cache), method.fits

    assert run()[1] == 1
    swap(own, "queries/q0.jpg", "query/0000005.jpg", shared_data)
    record, fits = run()
    assert (record["descriptors_computed"], fits) == ({"database": 0, "queries": 4}, 0)
    swap(own, "database/d3.jpg", "ref/0000009.jpg", shared_data)
    record, fits = run()
    assert (record["descriptors_computed"], fits) == ({"database": 6, "queries": 4}, 1)
    fresh = vprbench.create_method("fitted-test")
    scratch = evaluate(fresh, load_dataset(str(own)), ks=[1, 3], cache_dir=tmp_path / "scratch")
    assert record["recall"] == scratch["recall"] and record["top_predictions"] == scratch["top_predictions"]


def test_a_record_of_the_one_folder_layout_still_finds_its_stores(tmp_path, monkeypatch):
    """Records written before name one folder (context.store.folder) holding both splits."""
    from vprbench.store import folder as folder_module

    seen = []
    monkeypatch.setattr(folder_module.DescriptorStore, "recorded", lambda path, store: seen.append((path, store)))
    run_store({"context": {"store": {"folder": "m-1/d-2"}}}, "queries", tmp_path)
    run_store({"context": {"store": {"folders": {"queries": "m-1/d-queries-3"}}}}, "queries", tmp_path)
    assert seen == [(tmp_path / "stores" / "m-1/d-2" / "queries.h5", "m-1/d-2/queries"),
                    (tmp_path / "stores" / "m-1/d-queries-3" / "queries.h5", "m-1/d-queries-3/queries")]


def test_a_map_image_edited_while_fitting_leaves_no_fit_for_the_old_images(own, shared_data, tmp_path, monkeypatch):
    """Another process edits a map image while the fit reads the database: the fit (of the new
    bytes) must not be saved under the old images' key, to be reused once the edit is undone.
    Was: saved, and the next run on the original images reused it (other predictions)."""
    import store_helpers

    from vprbench.errors import VPRBenchError

    cache, fit = tmp_path / "cache", store_helpers.Fitted.fit

    def edited_meanwhile(self, database):
        swap(own, "database/d3.jpg", "ref/0000019.jpg", shared_data)
        return fit(self, database)

    monkeypatch.setattr(store_helpers.Fitted, "fit", edited_meanwhile)
    with pytest.raises(VPRBenchError, match=r"d3\.jpg changed"):
        evaluate(vprbench.create_method("fitted-test"), load_dataset(str(own)), ks=[1, 3], cache_dir=cache)
    assert not list(cache.rglob("fit_state.h5"))
    monkeypatch.setattr(store_helpers.Fitted, "fit", fit)
    swap(own, "database/d3.jpg", "ref/0000003.jpg", shared_data)  # the edit undone
    method = vprbench.create_method("fitted-test")
    record = evaluate(method, load_dataset(str(own)), ks=[1, 3], cache_dir=cache)
    scratch = evaluate(vprbench.create_method("fitted-test"), load_dataset(str(own)), ks=[1, 3],
                       cache_dir=tmp_path / "scratch")
    assert method.fits == 1 and record["top_predictions"] == scratch["top_predictions"]


def test_two_query_sets_of_a_fit_that_cannot_be_saved_keep_their_own_database_rows(own, shared_data, tmp_path):
    """A fit that cannot be saved differs run to run, so another query set on the same map refits
    and describes the map again. Was: into the shared database store, replacing the rows the
    first query set's record names (a run still searching them failed; its rerun described again)."""
    other = tmp_path / "b" / "own"
    shutil.copytree(own, other)
    for i in range(4):
        swap(other, f"queries/q{i}.jpg", f"query/{i + 4:07d}.jpg", shared_data)
    cache = tmp_path / "cache"

    def run(root):
        method = vprbench.create_method("unsaved-test")
        return evaluate(method, load_dataset(str(root)), ks=[1, 3], cache_dir=cache), method.fits

    first, _ = run(own)
    assert run(other)[0]["descriptors_computed"] == {"database": 6, "queries": 4}
    with h5py.File(run_store(first, "queries", cache).path) as f:
        fit = f.attrs["fit_id"]
    assert run_store(first, "database", cache).identity.fit_id == fit  # the first run's rows are still there
    again, fits = run(own)
    assert (again["descriptors_computed"], fits) == ({"database": 0, "queries": 0}, 0)
    assert again["top_predictions"] == first["top_predictions"]
