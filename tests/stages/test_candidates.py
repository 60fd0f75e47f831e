"""Frozen candidates: exported once, re-rankers start from them; a file of another protocol or retriever is refused."""
import dataclasses
import os
import shutil
import time

import h5py
import numpy as np
import pytest

from vprbench.errors import VPRBenchError
from vprbench.evaluation import evaluate
from vprbench.spec import RunSettings, resolve_spec
from vprbench.evaluation.pipeline import export_candidates

RERANK = [{"name": "aqe", "k": 20, "n": 2}]


@pytest.fixture(scope="module")
def exported(shared_data, stage_cache, tmp_path_factory):
    path = tmp_path_factory.mktemp("candidates") / "hog.h5"
    settings = RunSettings(data_dir=shared_data, cache_dir=stage_cache)
    written = export_candidates(resolve_spec("hog", "corridor", data_dir=shared_data), settings, path, k=30)
    assert written == {"file": str(path), "queries": 111, "k": 30}
    return path, settings


def test_a_rerank_from_the_file_is_the_rerank_from_a_search(shared_data, exported):
    path, settings = exported
    spec = resolve_spec("hog", "corridor", stages=RERANK, ks=(1, 5), data_dir=shared_data)
    searched = evaluate(spec, settings)
    frozen = evaluate(spec, dataclasses.replace(settings, candidates=path))
    assert frozen["per_query"]["database_indices"] == searched["per_query"]["database_indices"]
    assert frozen["spec_key"] == searched["spec_key"]  # the same run, started from the same candidates
    assert frozen["context"]["candidates"]["file"] == str(path.resolve()) and frozen["context"]["candidates"]["k"] == 30
    assert len(frozen["context"]["candidates"]["sha256"]) == 64 and "candidates" not in searched["context"]
    with h5py.File(path) as f:
        assert f["indices"].shape == (111, 30) and f.attrs["protocol_id"] == "corridor:vpr-bench"


def edited(path, tmp_path, **attrs):
    copy = tmp_path / "edited.h5"
    copy.write_bytes(path.read_bytes())
    with h5py.File(copy, "a") as f:
        for key, value in attrs.items():
            if key == "indices":
                f["indices"][0, 0] = value
            else:
                f.attrs[key] = value
    return copy


@pytest.mark.parametrize("spec_parts, attrs, message", [
    ({}, {"protocol_hash": "0" * 16, "protocol_id": "corridor:other"},
     r"was exported under protocol corridor:other \(0000000000000000\), not this run's corridor:vpr-bench"),
    # before: accepted, its rows indexing another copy's images scored against this copy's ground truth
    ({}, {"images_key": "0" * 16}, "was exported on other images of corridor than this run's"),
    ({"options": {"resize": [32, 32]}}, {}, r"was exported by another retriever \(hog \{\}\), not this run's hog"),
    # before: 'another retriever (hog {}), not this run's hog {}', the store (or weights) that differ unnamed
    ({"store_dtype": "float16"}, {}, r"another retriever \(hog \{\}, store float32\), not this run's hog \{\}, store float16:"),
    ({"stages": [{"name": "aqe", "k": 50}]}, {}, r"holds the top 30 per query, but this run needs 50"),
    ({}, {"indices": 5000}, "holds indices outside the 111 database images"),
    ({}, {"format": "something"}, "is not a vprbench candidates file"),
    # before: tracebacks (an array's truth value, a UTF-8 decode, int('abc'), json's recursion, info["dim"])
    ({}, {"images_key": np.array(["a", "b"], dtype=h5py.string_dtype())}, "its attribute images_key holds ndarray"),
    ({}, {"protocol_hash": np.bytes_(b"\xff\xfe")}, "its attribute protocol_hash cannot be read"),
    ({}, {"version": "abc"}, "holds version abc, not a vprbench candidates version"),
    ({}, {"retriever_key": "0", "retriever_spec": "[" * 100_000 + "]" * 100_000},
     r"exported by another retriever \(an unreadable spec\)"),
    ({}, {"search": "[1, 2]"}, r"its search attribute does not give the descriptors' dimension \(dim\)"),
    # before: the whole 100,000-character name in the message
    ({}, {"retriever_key": "0", "retriever_spec": '{"method": "%s"}' % ("x" * 100_000)},
     r"exported by another retriever \(x{77}\.\.\. None\), not"),
    ({"stages": []}, {}, "this run has no stage: add --rerank STAGE"),
    # before: accepted, the file ignored by the sequence stage yet named in the record
    ({"stages": [{"name": "diagonal", "length": 3}, *RERANK]}, {},
     "sequence stage 'diagonal' runs first and matches every query against the whole database, ignoring them"),
])
def test_a_file_that_does_not_fit_the_run_is_refused(shared_data, exported, tmp_path, spec_parts, attrs, message):
    path, settings = exported
    parts = {"stages": RERANK, "ks": (1, 5), **spec_parts}
    spec = resolve_spec("hog", "corridor", data_dir=shared_data, **parts)
    with pytest.raises(VPRBenchError, match=message):
        evaluate(spec, dataclasses.replace(settings, candidates=edited(path, tmp_path, **attrs)))


def test_a_file_of_another_content_under_a_cached_name_is_refused(shared_data, exported):
    """What an option named in the cache (an AnyLoc vocabulary 'urban', imported or fitted in another cache) is part
    of the retriever. Before: a file exported with one 'urban' was taken by a run whose 'urban' holds other centres."""
    path, settings = exported
    spec = resolve_spec("hog", "corridor", stages=RERANK, ks=(1, 5), data_dir=shared_data)
    spec = spec.model_copy(update={"found": {"vocabulary": "sha256:" + "1" * 64}})
    with pytest.raises(VPRBenchError, match=r"another retriever \(hog \{\}, cached files \{\}\), not this run's hog \{\}, "
                                            r"cached files \{'vocabulary': 'sha256:1{64}'\}"):
        evaluate(spec, dataclasses.replace(settings, candidates=path))


def _replaced(name, **dataset):
    def edit(f):
        del f[name]
        f.create_dataset(name, **dataset)
    return edit


#: arrays of a hand-made file, each refused from its header before it is read; before: a traceback
#: (text scores, a group), an "out of memory, lower --batch-size" (a header claiming 2**40 columns),
#: complex scores cut to their real part, scores read from another file on the machine
ARRAYS = {
    "text-scores": _replaced("scores", data=np.full((111, 30), b"x")),
    "complex-scores": _replaced("scores", data=np.ones((111, 30), np.complex64)),
    "group-indices": lambda f: (f.__delitem__("indices"), f.create_group("indices")),
    "huge-indices": _replaced("indices", shape=(111, 2**40), dtype="i8", chunks=(1, 1024)),
    "huge-all-zero": _replaced("all_zero", shape=(2**40,), dtype="u1", chunks=(1024,)),
    "external-scores": _replaced("scores", shape=(111, 30), dtype="f4", external=[("/etc/hostname", 0, 2**20)]),
    # before: followed, the arrays read from another file (outside the sha256 recorded), or a named pipe (a hang)
    "linked-indices": lambda f: (f.__delitem__("indices"),
                                 f.__setitem__("indices", h5py.ExternalLink(f.filename + ".other", "/indices"))),
}


@pytest.mark.parametrize("edit", ARRAYS)
def test_arrays_a_file_cannot_hold_are_refused_before_they_are_read(shared_data, exported, tmp_path, edit):
    path, settings = exported
    copy = edited(path, tmp_path)
    with h5py.File(copy, "a") as f:
        ARRAYS[edit](f)
    spec = resolve_spec("hog", "corridor", stages=RERANK, ks=(1, 5), data_dir=shared_data)
    name = edit.split("-", 1)[1].replace("-", "_")
    if edit == "linked-indices":  # the link's target: the export's own file, whose arrays would fit
        shutil.copy(path, str(copy) + ".other")
    with pytest.raises(VPRBenchError, match=rf"Candidates file .*: its {name} holds .*, not at most [\d,]+ real "
                                            "numbers stored in the file; export it again"):
        evaluate(spec, dataclasses.replace(settings, candidates=copy))


def test_a_file_from_another_copy_of_the_dataset_is_refused(shared_data, exported, tmp_path):
    """Same name and protocol, two reference images swapped: the file's rows index the other copy's images."""
    _, settings = exported
    ref = tmp_path / "copy" / "corridor" / "ref"
    shutil.copytree(shared_data / "corridor", ref.parent)
    first, other = ref / "0000000.jpg", ref / "0000050.jpg"
    first_bytes = first.read_bytes()
    first.write_bytes(other.read_bytes())
    other.write_bytes(first_bytes)
    path = tmp_path / "copy.h5"
    export_candidates(resolve_spec("hog", "corridor", data_dir=tmp_path / "copy"),
                      dataclasses.replace(settings, data_dir=tmp_path / "copy"), path, k=30)
    spec = resolve_spec("hog", "corridor", stages=RERANK, ks=(1, 5), data_dir=shared_data)
    with pytest.raises(VPRBenchError, match="was exported on other images of corridor than this run's"):
        evaluate(spec, dataclasses.replace(settings, candidates=path))


def test_a_file_of_another_dataset_is_named_as_such(shared_data, exported, tmp_path):
    """docs/stages.md: a file of another protocol is refused naming both protocols. Corridor's file on a smaller
    folder of one's own was refused as damaged instead ('its indices holds int64 (111, 30), not at most 6 real
    numbers stored in the file; export it again'): the arrays' size bound came before the protocol."""
    from own_folders import corridor_folder

    path, settings = exported
    own = corridor_folder(shared_data, tmp_path / "mine", database=3, queries=2)
    spec = resolve_spec("hog", str(own), stages=[{"name": "aqe", "k": 3, "n": 2}], ks=(1,), data_dir=shared_data)
    with pytest.raises(VPRBenchError, match=r"was exported under protocol corridor:vpr-bench \(f60ac2fa1d51bc67\), "
                                            r"not this run's mine:own .*export candidates on this dataset and protocol"):
        evaluate(spec, dataclasses.replace(settings, candidates=path))


def test_an_export_removes_what_a_killed_export_left(shared_data, exported, tmp_path):
    """Before: the temporary file of an export killed while writing stayed beside --out for good."""
    _, settings = exported
    left = tmp_path / ".hog.h5.killed.tmp"
    left.write_bytes(b"half")
    os.utime(left, (time.time() - 7200,) * 2)  # a live writer's would be younger
    export_candidates(resolve_spec("hog", "corridor", data_dir=shared_data), settings, tmp_path / "hog.h5", k=5)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["hog.h5"]


def test_export_needs_a_retriever_without_stages(shared_data, exported, tmp_path):
    _, settings = exported
    with pytest.raises(VPRBenchError, match="candidates export writes a retriever's candidates"):
        export_candidates(resolve_spec("hog", "corridor", stages=RERANK, ks=(1,), data_dir=shared_data), settings,
                          tmp_path / "x.h5")
    with pytest.raises(VPRBenchError, match="500 candidates per query asked for, but the database of corridor holds 111"):
        export_candidates(resolve_spec("hog", "corridor", data_dir=shared_data), settings, tmp_path / "x.h5", k=500)
    assert not (tmp_path / "x.h5").exists()


def test_a_file_searched_deeper_by_an_approximate_index_is_not_a_shallower_run(shared_data, stage_cache, tmp_path):
    """hnsw exported with --k 111 searched a shortlist of 111; a re-ranking of its top 100 took the file for the run
    that searches a shortlist of 100 (one spec key, other candidates). It is refused, and taken by the run as deep."""
    settings = RunSettings(data_dir=shared_data, cache_dir=stage_cache)
    path = tmp_path / "hnsw.h5"
    export_candidates(resolve_spec("hog", "corridor", search="hnsw", data_dir=shared_data), settings, path, k=111)
    rerank = {"stages": [{"name": "aqe", "k": 100, "n": 2}], "ks": (1, 5), "data_dir": shared_data}
    shallow = resolve_spec("hog", "corridor", search="hnsw", **rerank)
    with pytest.raises(VPRBenchError, match=r"exported by another retriever \(hog \{.*\}, search .*'shortlist': 111"):
        evaluate(shallow, dataclasses.replace(settings, candidates=path))
    deep = resolve_spec("hog", "corridor", search={"index": "hnsw", "options": {"shortlist": 111}}, **rerank)
    frozen = evaluate(deep, dataclasses.replace(settings, candidates=path))
    assert frozen["spec_key"] != shallow.key
    assert frozen["per_query"]["database_indices"] == evaluate(deep, settings)["per_query"]["database_indices"]


def test_the_export_command_takes_the_index_options_evaluate_takes(shared_data, stage_cache, tmp_path, cli):
    """`evaluate --index hnsw --index-option hnsw_m=16 --candidates FILE` could never start from a file: `candidates
    export` had --index but no --index-option, so no file of that retriever could be written."""
    out, search = tmp_path / "hnsw16.h5", ["--index", "hnsw", "--index-option", "hnsw_m=16"]
    where = ["--data-dir", shared_data, "--cache-dir", stage_cache, "--quiet"]
    code, _, err = cli("candidates", "export", "--method", "hog", "--dataset", "corridor", "--k", 20, *search,
                       "--out", out, *where)
    assert code == 0, err
    code, _, err = cli("evaluate", "--method", "hog", "--dataset", "corridor", "--k", 1, 5, *search, "--rerank", "aqe",
                       "--rerank-k", 20, "--candidates", out, *where)
    assert code == 0, err


def test_a_file_flagging_queries_all_zero_that_are_not_is_refused(shared_data, exported, tmp_path):
    """Before: every query flagged all zero was taken, each counted a failure: R@1 0 stored under the genuine key."""
    path, settings = exported
    copy = edited(path, tmp_path)
    with h5py.File(copy, "a") as f:
        f["all_zero"][5] = 1
    spec = resolve_spec("hog", "corridor", stages=RERANK, ks=(1, 5), data_dir=shared_data)
    with pytest.raises(VPRBenchError, match=r"edited.h5: its all_zero flags say query 5's descriptor is all zero, but "
                                            "this run's is not: export it again"):
        evaluate(spec, dataclasses.replace(settings, candidates=copy))


@pytest.mark.parametrize("edit", ["rows-moved", "scores-halved"])
def test_a_file_whose_rows_are_not_the_retrievers_is_refused(shared_data, exported, tmp_path, edit):
    """The file's candidates scored again from the run's descriptors. Before: a file whose rows were moved one query
    on was re-ranked and stored under the genuine run's key (hog + aqe@10 R@1 4.5 on the board instead of 45.9)."""
    path, settings = exported
    copy = edited(path, tmp_path)
    with h5py.File(copy, "a") as f:
        indices, scores = f["indices"][...], f["scores"][...]
        if edit == "rows-moved":
            f["indices"][...], f["scores"][...] = np.roll(indices, 1, 0), np.roll(scores, 1, 0)
        else:  # the order kept, the scores not the retriever's
            f["scores"][...] = scores / 2
    spec = resolve_spec("hog", "corridor", stages=RERANK, ks=(1, 5), data_dir=shared_data)
    with pytest.raises(VPRBenchError, match=r"Candidates file .*edited.h5: query 0's candidate \d+ has the score .* "
                                            "there, but .* from this run's descriptors: its rows are not this "
                                            "retriever's candidates"):
        evaluate(spec, dataclasses.replace(settings, candidates=copy))
