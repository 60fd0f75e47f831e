"""Stores of any size: created whole, resumed row by row, read as complete only when their own content says so."""
import h5py
import numpy as np
import pytest

import vprbench
from vprbench.datasets import load_dataset
from vprbench.errors import VPRBenchError
from runs import evaluate_method as evaluate
from vprbench.store import DescriptorStore, RowsIdentity, RowWriter, StoreFolder, create_rows_file, inspect_rows_file


def identity(n: int, dtype="float32", fit_id="none", start=0, stop=None, store="m-1/d-2/database") -> RowsIdentity:
    names = [f"images/{i:07d}/place@{i}.jpg" for i in range(n)]
    stop = n if stop is None else stop
    return RowsIdentity(store=store, start=start, stop=stop, total=n, fit_id=fit_id, dtype=dtype,
                        fingerprint='{"method": "m"}', names=names[start:stop])


def rows(first: int, last: int, dim: int) -> np.ndarray:
    return np.arange(first * dim, last * dim, dtype=np.float32).reshape(-1, dim) / 7.0


@pytest.mark.parametrize("n,dim", [(5_000, 96), (100_000, 16)])
def test_store_of_n_rows_resumes_and_is_complete_only_when_every_row_is(tmp_path, n, dim):
    path, ident = tmp_path / "database.h5", identity(n)
    create_rows_file(path, ident, dim)
    assert inspect_rows_file(path, ident).status == "partial"
    writer = RowWriter(path, ident)
    # an interrupted run: batches of 1,000 done with gaps between them, and scattered single rows
    written = np.concatenate([np.arange(start, min(n, start + 1000)) for start in range(0, n, 2000)]
                             + [np.arange(1001, min(n, 1999), 3)])
    written = np.unique(written)
    for start in range(0, len(written), 512):
        batch = written[start:start + 512]
        writer.write(batch, rows(0, n, dim)[batch])
    writer.close()

    found = inspect_rows_file(path, ident)  # reopened by a later run: the flags say what is left
    assert found.status == "partial" and np.array_equal(np.flatnonzero(found.done), written)
    with pytest.raises(VPRBenchError, match="not complete"):
        DescriptorStore(path, ident)
    writer = RowWriter(path, ident)
    missing = np.flatnonzero(~found.done)
    writer.write(missing, rows(0, n, dim)[missing])
    writer.finish()

    store = DescriptorStore(path, ident)
    assert (store.row_count, store.dim, store.dtype, store.folder) == (n, dim, "float32", tmp_path)
    np.testing.assert_array_equal(store.read_rows(0, n), rows(0, n, dim))
    np.testing.assert_array_equal(store.read_rows(n - 3, n), rows(n - 3, n, dim))
    at = np.array([0, 1, 1, 17, n // 2, n - 1])
    np.testing.assert_array_equal(store.read_rows_at(at), rows(0, n, dim)[at])
    with h5py.File(path) as f:
        assert f["names"].asstr()[n - 1] == ident.names[-1]


def complete_store(tmp_path, n=40, dim=8, **kwargs):
    path, ident = tmp_path / "queries.h5", identity(n, **kwargs)
    create_rows_file(path, ident, dim)
    writer = RowWriter(path, ident)
    writer.write(np.arange(n), rows(0, n, dim))
    writer.finish()
    return path, ident


def test_completion_is_read_from_the_content_not_the_file_name(tmp_path):
    path, ident = complete_store(tmp_path)
    assert inspect_rows_file(path, ident).status == "complete"
    with h5py.File(path, "r+") as f:  # one row's flag lost (as a crash between rows and flags would)
        f["done"][5] = 0
    assert inspect_rows_file(path, ident).status == "partial"
    with h5py.File(path, "r+") as f:
        f["done"][5] = 1
        f["complete"][()] = 0  # every row done but the completion byte never written
    assert inspect_rows_file(path, ident).status == "partial"
    with h5py.File(path, "r+") as f:
        f["complete"][()] = 1
    store = DescriptorStore(path, ident)
    with h5py.File(path, "r+") as f:  # changed after it was opened: the next read checks again
        f["done"][0] = 0
    with pytest.raises(VPRBenchError, match="not complete"):
        store.read_rows(0, 2)


def test_other_names_counts_or_fits_are_never_read_as_this_store(tmp_path):
    path, ident = complete_store(tmp_path)
    renamed = RowsIdentity(**{**ident.__dict__, "names": ident.names[:-1] + ["another.jpg"]})
    assert inspect_rows_file(path, renamed).status == "foreign"
    longer = identity(41)
    assert inspect_rows_file(path, longer).status == "foreign"
    assert "stop" in inspect_rows_file(path, longer).reason
    refitted = RowsIdentity(**{**ident.__dict__, "fit_id": "sha256:other"})
    assert inspect_rows_file(path, refitted).status == "stale"
    path.write_bytes(path.read_bytes()[:300])  # torn
    assert inspect_rows_file(path, ident).status == "torn"


def test_float16_store_halves_the_disk_and_reads_float32(tmp_path):
    small, ident16 = complete_store(tmp_path / "a", n=2000, dim=64, dtype="float16")
    large, _ = complete_store(tmp_path / "b", n=2000, dim=64)
    with h5py.File(small) as a, h5py.File(large) as b:
        assert a["descriptors"].id.get_storage_size() * 2 == b["descriptors"].id.get_storage_size()
    read = DescriptorStore(small, ident16).read_rows(0, 2000)
    assert read.dtype == np.float32
    np.testing.assert_allclose(read, rows(0, 2000, 64), rtol=1e-3)


def test_a_float16_runs_record_gives_the_bytes_its_map_keeps(shared_data, tmp_path, cli):
    """Was: descriptor_bytes 4 per dimension whatever the store kept, so the board's bytes-per-image
    column showed a float16 store at float32's size."""
    import json

    found = {}
    for dtype in ("float32", "float16"):
        code, out, err = cli("evaluate", "--method", "hog", "--resize", 64, 64, "--dataset", "corridor", "--k", 1,
                             "--store-dtype", dtype, "--data-dir", shared_data, "--cache-dir", tmp_path, "--json")
        assert code == 0, err
        found[dtype] = json.loads(out)
    assert found["float32"]["descriptor_dim"] == found["float16"]["descriptor_dim"] == 441
    assert found["float32"]["descriptor_bytes"] == 4 * 441 and found["float16"]["descriptor_bytes"] == 2 * 441


def test_fit_state_written_whole(tmp_path):
    folder = StoreFolder("m", {"a": 1}, "d", {"database": "x"}, tmp_path)
    assert folder.read_fit_state() is None
    first = folder.write_fit_state({"centres": np.ones((4, 3), np.float32)})
    state, fit_id = folder.read_fit_state()
    assert fit_id == first and state["centres"].shape == (4, 3)
    folder.fit_path.write_bytes(b"torn")  # not one of ours: discarded, so the method fits again
    with pytest.warns(UserWarning, match="Discarding"):
        assert folder.read_fit_state() is None
    assert not folder.fit_path.exists()


def test_a_fit_state_copied_from_another_store_is_not_used(tmp_path):
    """Its fit id names its content, not the database it was fitted on: a vocabulary fitted on
    one dataset's images, copied into another's store folder, was loaded as that dataset's."""
    import shutil

    theirs = StoreFolder("m", {"a": 1}, "other", {"database": "y"}, tmp_path)
    theirs.write_fit_state({"centres": np.ones((4, 3), np.float32)})
    ours = StoreFolder("m", {"a": 1}, "d", {"database": "x"}, tmp_path)
    ours.fit_path.parent.mkdir(parents=True)
    shutil.copyfile(theirs.fit_path, ours.fit_path)
    with pytest.warns(UserWarning, match=r"Discarding .*fit_state.h5: .* fitted for store 'm-.*/other-"):
        assert ours.read_fit_state() is None
    assert not ours.fit_path.exists() and theirs.read_fit_state() is not None


def test_store_key_covers_options_a_fingerprint_forgets(shared_data):
    dataset = load_dataset("corridor", shared_data)
    small = evaluate(vprbench.create_method("forgetful-test", size=4), dataset)
    large = evaluate(vprbench.create_method("forgetful-test", size=6), dataset)
    assert large["descriptors_computed"] == {"database": 111, "queries": 111}
    assert (small["descriptor_dim"], large["descriptor_dim"]) == (16, 36)
    assert large["method_fingerprint"]["settings"] == {"size": 6}


def test_empty_fit_state_means_fit_again_never_resume_unfitted(shared_data, tmp_path, monkeypatch):
    """Unsaved fits differ run to run: an interrupted run's rows are never mixed with a new fit's."""
    dataset = load_dataset("corridor", shared_data)
    method = vprbench.create_method("unsaved-test")
    calls = {"n": 0}
    real = method.describe

    def interrupted(items):
        calls["n"] += 1
        if calls["n"] == 14:  # database finished (12 batches), queries underway
            raise KeyboardInterrupt
        return real(items)

    monkeypatch.setattr(method, "describe", interrupted)
    with pytest.raises(KeyboardInterrupt):
        evaluate(method, dataset)
    again = vprbench.create_method("unsaved-test")
    with pytest.warns(UserWarning, match="it was computed with fit 'unsaved:.*'; it is recomputed") as caught:
        record = evaluate(again, dataset)
    assert len(caught) == 2  # the database's and the queries' partial stores
    assert again.fits == 1  # fitted again, not resumed unfitted
    assert record["descriptors_computed"] == {"database": 111, "queries": 111}  # nothing of the old fit kept
    warm = vprbench.create_method("unsaved-test")
    assert evaluate(warm, dataset)["descriptors_computed"] == {"database": 0, "queries": 0} and warm.fits == 0


def test_warm_store_computes_nothing_and_reuses_the_saved_fit(shared_data):
    dataset = load_dataset("corridor", shared_data)
    cold_method = vprbench.create_method("fitted-test")
    cold = evaluate(cold_method, dataset)
    assert cold["descriptors_computed"] == {"database": 111, "queries": 111} and cold_method.fits == 1
    warm_method = vprbench.create_method("fitted-test")
    warm = evaluate(warm_method, dataset)
    assert warm["descriptors_computed"] == {"database": 0, "queries": 0} and warm_method.fits == 0
    assert warm["recall"] == cold["recall"]


def test_rows_written_in_runs_far_apart_land_at_their_own_rows(tmp_path):
    """A resumed run writes two runs of rows too far apart to rewrite as one block: each run of
    rows must take its own descriptors, not the first ones of the batch."""
    n, dim = 200, 4
    path, ident = tmp_path / "database.h5", identity(n)
    create_rows_file(path, ident, dim)
    writer = RowWriter(path, ident)
    batch = np.array([0, 1, 2, 150, 151])
    writer.write(batch, rows(0, n, dim)[batch])
    rest = np.setdiff1d(np.arange(n), batch)
    writer.write(rest, rows(0, n, dim)[rest])
    writer.finish()
    np.testing.assert_array_equal(DescriptorStore(path, ident).read_rows(0, n), rows(0, n, dim))


def test_float16_rows_at_given_indices_read_in_order_as_float32(tmp_path):
    """Rows close together are read as one slice, far apart ones one by one: both keep the order
    and the repeats asked for, and give float32 whatever the stored type."""
    path, ident = complete_store(tmp_path, n=2000, dim=64, dtype="float16")
    store = DescriptorStore(path, ident)
    for asked in ([3, 3, 4, 5], [0, 0, 1999]):
        read = store.read_rows_at(asked)
        assert read.dtype == np.float32 and read.shape == (len(asked), 64)
        np.testing.assert_allclose(read, rows(0, 2000, 64)[asked], rtol=1e-3)
