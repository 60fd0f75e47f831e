"""Result records in the wrong place of a shared cache: copied over another protocol's record or
into another row's folder, or a stray file at the results root. Such a record is never served for
the folder's run (its protocol and row are read from it, not from where it lies), and each is named
in a warning once per process."""
from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

from vprbench.evaluation.served import find_result
from vprbench.spec import resolve_spec


def _own_corridor(shared_data, own: Path) -> Path:
    """Six corridor places as a folder of one's own, positioned by frame."""
    rows = ["image,frame"]
    for i in range(6):
        for split, source, prefix in (("database", "ref", "d"), ("queries", "query", "q")):
            (own / split).mkdir(parents=True, exist_ok=True)
            shutil.copy(shared_data / "corridor" / source / f"{i:07d}.jpg", own / split / f"{prefix}{i}.jpg")
            rows.append(f"{split}/{prefix}{i}.jpg,{i}")
    (own / "positions.csv").write_text("\n".join(rows) + "\n")
    return own


def test_a_record_of_another_protocol_copied_over_one_is_not_served(shared_data, tmp_path, cli, monkeypatch):
    """Two runs of hog on one folder of one's own, radius 1 frame and then 2 (two protocols, one
    row). Was: the radius-2 run's record copied over the radius-1 one (same file name) was served
    by find_result for the radius-1 spec (R@1 50.0 instead of 33.3), so `vprbench run` would show
    it as that cell and never run it: the folder's name was trusted, not the record's protocol."""
    own, cache = _own_corridor(shared_data, tmp_path / "own"), tmp_path / "cache"
    monkeypatch.chdir(tmp_path)
    runs = {}
    for radius in (2, 1):
        (own / "dataset.toml").write_text(f"radius = {radius}\n")
        code, out, err = cli("evaluate", "--method", "hog", "--dataset", "./own", "--k", "1", "2", "--quiet", "--json",
                             "--cache-dir", cache)
        assert code == 0, err
        runs[radius] = json.loads(out)
    spec = resolve_spec("hog", "./own", ks=(1, 2), cache_dir=cache)  # radius 1
    assert spec.dataset.protocol_hash == runs[1]["protocol"]["hash"] != runs[2]["protocol"]["hash"]
    assert find_result(spec, cache)["recall"] == runs[1]["recall"] == {"1": 33.333333, "2": 66.666667}
    mine = next(cache.glob(f"results/{runs[1]['protocol']['hash']}/*/*.json"))
    theirs = next(cache.glob(f"results/{runs[2]['protocol']['hash']}/*/*.json"))
    shutil.copy(theirs.with_suffix(".npz"), mine.parent)
    shutil.copy(theirs, mine)  # the other run's record under this one's name
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert find_result(spec, cache) is None  # not this protocol's run: the cell is evaluated again
    row = runs[1]["row_key"]
    assert [str(w.message) for w in caught] == [  # was: without a word
        f"{mine} does not count as a result: it lies among the runs of protocol {runs[1]['protocol']['hash']}, row "
        f"{row}, but holds a run of protocol {runs[2]['protocol']['hash']}, row {row} (copied or moved there; nothing "
        "was deleted)."]


def test_a_record_in_the_wrong_place_is_named_once_per_process_not_per_look_up(shared_data, tmp_path, cli, monkeypatch):
    """A record copied into another row's folder, and a file at the results root that is no record (it
    stays where it is). Was: each look-up that met them said so again (a sweep looks three times per
    cell; the API showed each). Now each is named once per process (a command), again once changed;
    neither counts, however often looked up."""
    (_own_corridor(shared_data, tmp_path / "own") / "dataset.toml").write_text("radius = 1\n")
    cache = tmp_path / "cache"
    monkeypatch.chdir(tmp_path)
    code, _, err = cli("evaluate", "--method", "hog", "--dataset", "./own", "--k", "1", "--quiet", "--cache-dir", cache)
    assert code == 0, err
    record = next(cache.glob("results/*/*/*.json"))
    other = resolve_spec("hog", "./own", options={"cell": 8}, ks=(1,), cache_dir=cache)  # another row, never run
    folder = cache / "results" / other.dataset.protocol_hash / other.row_key
    folder.mkdir(parents=True)
    for made in (record, record.with_suffix(".npz")):
        shutil.copy(made, folder)
    stray = cache / "results" / "stray.json"
    stray.write_text("{}")

    def said() -> list[str]:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            for _ in range(3):
                assert find_result(other, cache) is None
        return [str(w.message) for w in caught]

    first = said()
    assert len(first) == 2, first
    assert first[0].startswith(f"{stray} stays where it is") and first[1].startswith(
        f"{folder / record.name} does not count as a result: it lies among the runs of protocol")
    assert said() == []  # known already in this process
    stray.write_text('{"changed": true}')
    again = said()
    assert len(again) == 1 and again[0].startswith(f"{stray} stays where it is"), again
