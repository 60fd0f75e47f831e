"""Every row of a store carries the crc32 written with it: a changed byte on disk is caught on
read, the store discarded under its folder's lock and recomputed; stores without checksums
(an earlier format) are recomputed, never trusted."""
import h5py
import numpy as np
import pytest

import vprbench
from runs import evaluate_method as evaluate
from vprbench.datasets import load_dataset
from vprbench.errors import VPRBenchError
from vprbench.store import DamagedRows, DescriptorStore, RowsIdentity, RowWriter, create_rows_file
from vprbench.store.rows_file import merge_rows_files, row_checksums


def identity(n, dtype="float32", start=0, stop=None):
    stop = n if stop is None else stop
    return RowsIdentity(store="m-1/d-2/database", start=start, stop=stop, total=n, fit_id="none", dtype=dtype,
                        fingerprint="{}", names=[f"{i}.jpg" for i in range(start, stop)])


def written(path, ident, values):
    create_rows_file(path, ident, values.shape[1])
    writer = RowWriter(path, ident)
    writer.write(np.arange(ident.start, ident.stop), values)
    writer.finish()
    writer.close()


def flip_byte(path, row: int, byte: int = 1) -> None:
    """XOR one byte of row `row`'s stored descriptor, in place on disk (as a bad disk or an edit would)."""
    with h5py.File(path, "r") as f:
        data = f["descriptors"]
        at = data.id.get_offset() + row * data.shape[1] * data.dtype.itemsize + byte
    with open(path, "r+b") as file:
        file.seek(at)
        old = file.read(1)
        file.seek(at)
        file.write(bytes([old[0] ^ 0x10]))


def values(n=300, dim=24, seed=0):
    return np.random.default_rng(seed).normal(size=(n, dim)).astype(np.float32)


def test_checksums_are_the_crc32_of_the_stored_bytes_of_each_row(tmp_path):
    import zlib

    for dtype in ("float32", "float16"):
        path, ident, x = tmp_path / f"{dtype}.h5", identity(300, dtype), values()
        written(path, ident, x)
        with h5py.File(path, "r") as f:
            stored = f["checksums"][...]
        assert stored.dtype == np.uint32 and stored[7] == zlib.crc32(x[7].astype(dtype).tobytes())
        assert np.array_equal(stored, row_checksums(x.astype(dtype)))


@pytest.mark.parametrize("dtype, read", [(dtype, read) for dtype in ("float32", "float16")
                                         for read in ("slice", "into", "at", "verify", "view")
                                         if (dtype, read) != ("float16", "view")])  # float16 stores lend no rows
def test_a_flipped_byte_is_caught_on_read_and_the_store_discarded(tmp_path, dtype, read):
    path, ident, x = tmp_path / "database.h5", identity(300, dtype), values()
    written(path, ident, x)
    store = DescriptorStore(path, ident)
    np.testing.assert_allclose(store.read_rows(0, 300), x, rtol=1e-3)  # clean: every row checked, equal
    flip_byte(path, 123)
    store = DescriptorStore(path, ident)  # a later reader: complete by its flags, damaged by content
    reads = {"slice": lambda: store.read_rows(100, 200), "into": lambda: store.read_rows_into(
        120, 130, np.empty((10, 24), np.float32)), "at": lambda: store.read_rows_at([5, 123, 123, 250]),
        "verify": store.verify, "view": lambda: store.view_rows(100, 200)}
    with pytest.raises(DamagedRows, match=rf"Descriptor store {path} is damaged: row 123 no longer matches the "
                                          r"checksum written with it; it was discarded: run again to recompute it\.") as caught:
        reads[read]()
    assert "\n" not in str(caught.value) and not path.exists()
    with pytest.raises(VPRBenchError, match="has gone"):
        store.read_rows(0, 1)


def test_rows_already_checked_are_not_checked_again_until_the_file_changes(tmp_path):
    path, ident, x = tmp_path / "database.h5", identity(300), values()
    written(path, ident, x)
    store = DescriptorStore(path, ident)
    store.verify()
    assert store._checked.all()
    store.read_rows(0, 300)
    with h5py.File(path, "r+") as f:  # rewritten after it was checked: the reader checks it all again
        f["descriptors"][40] = -f["descriptors"][40]
    with pytest.raises(DamagedRows, match="row 40 no longer matches"):
        store.read_rows(0, 300)


def test_a_float32_store_lends_its_rows_from_its_file(tmp_path):
    """Search computes on a store's rows where they are: the file's pages, mapped read-only,
    checked like a read. A float16 store (widened on read) lends none."""
    import mmap

    path, ident, x = tmp_path / "database.h5", identity(300), values()
    written(path, ident, x)
    store = DescriptorStore(path, ident)
    view = store.view_rows(17, 290)
    assert np.array_equal(view, x[17:290]) and not view.flags.writeable
    assert isinstance(view.base.base.obj, mmap.mmap) and store._checked[17:290].all() and not store._checked[:17].any()
    assert store.view_rows(5, 5) is None and store.view_rows(0, 300).shape == (300, 24)
    with pytest.raises(ValueError, match="outside"):
        store.view_rows(250, 301)
    half = tmp_path / "half.h5"
    written(half, identity(300, "float16"), x)
    assert DescriptorStore(half, identity(300, "float16")).view_rows(0, 10) is None


def test_search_on_lent_store_rows_equals_search_on_read_rows(tmp_path, monkeypatch):
    """The same products whether rows are lent (a float32 store) or read into buffers (the
    same values in float64): bit for bit, at one chunk and at several (tiles of 512 rows)."""
    import vprbench.search.exact as search_module
    from vprbench.search.exact import exact_search
    from vprbench.row_sources import ArrayRows

    monkeypatch.setattr(search_module, "tile_rows", lambda dim: 512)
    db, q = values(3000, 64, 1), values(700, 64, 2)
    path = tmp_path / "database.h5"
    written(path, identity(3000), db)
    store = DescriptorStore(path, identity(3000))
    for budget in (10**9, 5 * 10**6):
        lent = exact_search(store, q, 10, memory_budget=budget)
        read = exact_search(ArrayRows(db.astype(np.float64)), q.astype(np.float64), 10, memory_budget=budget)
        np.testing.assert_array_equal(lent.scores, read.scores)
        np.testing.assert_array_equal(lent.indices, read.indices)
    assert lent.info["chunks"] > 1 and read.info["chunks"] > 1


def test_a_damaged_shard_is_refused_while_merging(tmp_path):
    x, parts = values(), []
    for start, stop in ((0, 150), (150, 300)):
        part = tmp_path / f"part{start}.h5"
        written(part, identity(300, start=start, stop=stop), x[start:stop])
        parts.append((part, identity(300, start=start, stop=stop)))
    merged = tmp_path / "database.h5"
    merge_rows_files(parts, merged, identity(300), 24)
    assert np.array_equal(DescriptorStore(merged, identity(300)).read_rows(0, 300), x)
    merged.unlink()
    flip_byte(parts[1][0], 10)
    with pytest.raises(DamagedRows, match=rf"{parts[1][0]} is damaged: row 160 no longer matches"):
        merge_rows_files(parts, merged, identity(300), 24)
    assert not merged.exists()


def _store_path(record, cache, split="database"):
    return cache / "stores" / record["context"]["store"]["folders"][split] / f"{split}.h5"


def test_a_flipped_byte_in_a_real_store_is_caught_discarded_and_recomputed(shared_data, tmp_path):
    dataset = load_dataset("corridor", shared_data)
    clean = evaluate(vprbench.create_method("thumb-test"), dataset, cache_dir=tmp_path)
    path = _store_path(clean, tmp_path)
    flip_byte(path, 57, byte=3)  # the high byte of one value of one database row
    with h5py.File(path, "r") as f:  # the attack is real: row 57 now differs from what was described
        assert not np.array_equal(row_checksums(f["descriptors"][57:58]), f["checksums"][57:58])
    with pytest.warns(UserWarning, match=rf"Descriptor store {path} was damaged \(row 57 no longer matches the "
                                         r"checksum written with it\); it was discarded and is recomputed"):
        again = evaluate(vprbench.create_method("thumb-test"), dataset, cache_dir=tmp_path)
    assert again["descriptors_computed"] == {"database": 111, "queries": 0}
    assert again["recall"] == clean["recall"]
    warm = evaluate(vprbench.create_method("thumb-test"), dataset, cache_dir=tmp_path)
    assert warm["descriptors_computed"] == {"database": 0, "queries": 0} and warm["recall"] == clean["recall"]


def test_a_store_without_checksums_is_recomputed_not_trusted(shared_data, tmp_path):
    dataset = load_dataset("corridor", shared_data)
    clean = evaluate(vprbench.create_method("thumb-test"), dataset, cache_dir=tmp_path)
    path = _store_path(clean, tmp_path, "queries")
    with h5py.File(path, "r+") as f:  # as the previous format wrote it: no checksums
        f.attrs["format"] = "vprbench-rows-2"
        del f["checksums"]
    with pytest.warns(UserWarning, match="written by an earlier vprbench, without row checksums; it is recomputed"):
        again = evaluate(vprbench.create_method("thumb-test"), dataset, cache_dir=tmp_path)
    assert again["descriptors_computed"] == {"database": 0, "queries": 111} and again["recall"] == clean["recall"]


def test_a_stores_content_key_names_its_rows_not_its_path(tmp_path):
    """What is fitted on a store's rows (a post-processor's state) is keyed by this: equal for the
    same rows anywhere, different when one row differs."""
    x = values()
    keys = []
    for name, rows in (("a.h5", x), ("b.h5", x), ("c.h5", np.vstack([x[:-1], x[-1:] + 1]))):
        written(tmp_path / name, identity(300), rows)
        keys.append(DescriptorStore(tmp_path / name, identity(300)).content_key())
    assert keys[0] == keys[1] != keys[2] and len(keys[0]) == 16
