"""A descriptor store, a fit state, a local-features segment or a sweep's claim replaced by a named pipe
(or a link to one): HDF5 (or the claim's reader) waited on it for good, so the run hung. Each is now taken
for a damaged file: discarded or set aside (said) and recomputed, or, read by the leaderboard, left out."""
import numpy as np
import pytest
from special_files import no_hang, pipe_at

from vprbench.stages.features import FeatureStore
from vprbench.store import DescriptorStore, StoreFolder, inspect_rows_file


def test_a_store_that_is_a_pipe_is_torn_and_left_out(tmp_path):
    folder = StoreFolder("m", {"a": 1}, "d", {"database": "x"}, tmp_path)
    folder.paths["database"].mkdir(parents=True)
    path = pipe_at(folder.store_path("database"))
    with no_hang():
        found = inspect_rows_file(path, folder.identity("database", ["a.jpg"], "none", "float32"))
        assert (found.status, found.reason) == ("torn", "it is a named pipe, device or socket, not a file")
        assert DescriptorStore.recorded(path, folder.keys["database"]) is None
        assert folder.recorded_fit_id("database") is None


def test_a_fit_state_that_is_a_pipe_is_discarded(tmp_path):
    folder = StoreFolder("m", {"a": 1}, "d", {"database": "x"}, tmp_path)
    folder.paths["database"].mkdir(parents=True)
    pipe_at(folder.fit_path)
    with no_hang():
        assert folder.fit_id_on_disk() is None
        with pytest.warns(UserWarning, match=r"Discarding \S+fit_state\.h5: the fit state cannot be read \(it is a "
                                             r"named pipe, device or socket, not a file\); it is recomputed\."):
            assert folder.read_fit_state() is None
    assert not folder.fit_path.exists() and not folder.fit_path.is_symlink()


def test_a_features_segment_that_is_a_pipe_is_discarded_and_computed_again(tmp_path):
    store = FeatureStore("sift", {"n": 1}, "set", {"database": "abc"}, tmp_path)
    store.path.mkdir(parents=True)
    segment = pipe_at(store.path / "database.1.h5")
    computed = []
    with no_hang():
        assert store.bytes_per_image() == 0
        with pytest.warns(UserWarning, match=rf"Local features {segment} are damaged \(it is a named pipe, device or "
                                             r"socket, not a file\); the file was discarded"):
            with store.opened("database", lambda row: computed.append(row) or {"points": np.ones((1, 2))}) as get:
                get(0)
    assert computed == [0] and [p.name for p in store.files("database")] == ["database.1.h5"]  # written anew


def test_a_claim_file_that_is_a_pipe_is_set_aside_unread(tmp_path):
    from vprbench.sweep.claims import _read_claim

    path = pipe_at(tmp_path / "cell.lease")
    with no_hang(), pytest.warns(UserWarning, match=rf"The claim file {path} cannot be read \(it is a named pipe, device "
                                                     rf"or socket, not a file\); it is set aside as {path}\.damaged"):
        assert _read_claim(path) is None
    assert not path.exists() and path.with_name("cell.lease.damaged").exists()


@pytest.mark.parametrize("kind", ["pipe", "zero"])
def test_a_liveness_file_that_is_a_pipe_or_device_is_made_again(tmp_path, kind):
    """<cell>.alive, which a claim opens to append and flock: a named pipe there made the open wait for a reader
    for good, so the sweep hung at its first cell."""
    from vprbench.sweep.claims import Claims

    claims = Claims(tmp_path)
    path = pipe_at(claims.folder / "cell.alive", kind)
    with no_hang(10):
        assert claims.claim("cell", lambda: False)[0] == "claimed"
    assert path.is_file() and not path.is_symlink()  # a file of its own again (a link's target untouched)
    claims.release("cell")


def test_a_lock_holders_note_or_a_lease_that_is_a_pipe_is_not_read(tmp_path):
    """The note naming a lock's holder (read while waiting for the lock) and a held cell's lease (read to know it
    is still this process's): a pipe in either's place made the read wait for a writer for good."""
    from vprbench.fsutil import _describe_holder
    from vprbench.sweep.claims import Claims

    path = tmp_path / "x.lock"
    pipe_at(path.with_name("x.lock.holder"))
    with no_hang(10):
        assert _describe_holder(path) == "another process"  # as said while waiting for the lock
    claims = Claims(tmp_path)
    assert claims.claim("cell", lambda: False)[0] == "claimed"
    pipe_at(claims.folder / "cell.lease")
    with no_hang(10):
        assert claims.still_mine("cell") is False


def test_a_folder_in_place_of_a_store_is_refused_once_and_left_as_it_is(tmp_path):
    """Was: warned "Discarding ...: it is recomputed", then stopped on "Is a directory": said twice, the first
    wrong. A folder is not the cache's to delete (it may hold anything): one line, nothing in it touched."""
    from vprbench.errors import VPRBenchError

    folder = StoreFolder("m", {"a": 1}, "d", {"database": "x"}, tmp_path)
    path = folder.store_path("database")
    (path / "kept").mkdir(parents=True)
    with pytest.raises(VPRBenchError, match=rf"^{path} is a folder where a descriptor store belongs: move or delete "
                                            r"it \(nothing in it was changed\), then run again\.$"):
        inspect_rows_file(path, folder.identity("database", ["a.jpg"], "none", "float32"))
    assert (path / "kept").is_dir()
