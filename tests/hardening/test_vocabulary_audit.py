"""Vocabulary files audited: centres that are no real numbers are refused, files without our
checksum (the authors' release, vocabularies saved before checksums) are checked by the CRC-32s
their zip writer stored, and `vocabulary show` / `list` say what the centres were learnt from."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import pytest
import torch

from vprbench.aggregation.vocabulary import Vocabulary, load_vocabulary
from vprbench.errors import VPRBenchError
from vprbench.methods.anyloc_lookup import resolve_vocabulary
from vprbench.methods.anyloc_vocabulary import save_to_cache
from vprbench.weights import file_sha256

RELEASED = Path("vocabularies") / "anyloc-dinov2_vitg14-l31-value-c32"


def centres(dtype=torch.float32) -> torch.Tensor:
    return (torch.arange(32 * 1536, dtype=torch.float32).reshape(32, 1536) % 97 / 97).to(dtype)


def nan_at(cluster, column, value=float("nan")):
    c = centres()
    c[cluster, column] = value
    return c


BAD = {
    "nan": (nan_at(3, 5), "has 1 NaN or infinite value(s) in its centres (first nan at cluster 3, dim 5), expected finite"),
    "inf": (nan_at(7, 0, float("-inf")), "(first -inf at cluster 7, dim 0), expected finite numbers"),
    "int": (centres().long(), "holds int64 values, expected floating-point centres (float32)"),
    "bool": (centres() > 0.5, "holds bool values, expected floating-point centres"),
    "complex": (torch.complex(centres(), centres()), "holds complex64 values, expected floating-point centres"),
    "meta": ({"centres": centres(), "meta": "indoor"}, "has a 'meta' entry that is no table of named values (str)"),
    # was imported, then shown as "32 clusters x 1536 dims" beside "clusters: 64" and cached so
    "clusters": ({"centres": centres(), "meta": {"clusters": 64, "backbone": "dinov2_vitg14"}},
                 "says it has 64 clusters but holds 32 centres (edited by hand?)"),
}


@pytest.mark.parametrize("name", list(BAD))
def test_centres_that_are_no_real_numbers_are_refused(name, tmp_path, cli):
    """Was: NaN, infinite, whole-number, truth-value and complex centres were imported (complex ones
    losing their imaginary part with a torch warning), and a 'meta' that is no table was a traceback."""
    content, said = BAD[name]
    path = tmp_path / f"{name}.pt"
    torch.save(content, path)
    code, out, err = cli("vocabulary", "import", path, "--source", "mine", "--cache-dir", tmp_path / "cache")
    assert (code, out) == (1, "") and err.startswith(f"error: Vocabulary file {path} ") and said in err
    assert err.count("\n") == 1 and "Traceback" not in err and not (tmp_path / "cache" / "vocabularies").exists()


def test_an_npy_whose_header_claims_more_than_the_file_holds_is_refused_unread(tmp_path, cli):
    """Was: the 64 TiB its header claims allocated first: "out of memory, lower --batch-size"."""
    import numpy as np

    path = tmp_path / "centres.npy"
    with open(path, "wb") as handle:
        np.lib.format.write_array_header_1_0(handle, {"descr": "<f4", "fortran_order": False, "shape": (2**30, 2**14)})
        handle.write(bytes(64))
    code, out, err = cli("vocabulary", "import", path, "--source", "mine", "--cache-dir", tmp_path / "cache")
    assert (code, out) == (1, "") and err.startswith(f"error: Cannot read vocabulary file {path}: it is truncated")
    assert err.count("\n") == 1 and "Traceback" not in err and not (tmp_path / "cache" / "vocabularies").exists()


def data_offset(path: Path, member_suffix: str) -> int:
    """Where the bytes of the zip member ending in `member_suffix` start in the file."""
    with zipfile.ZipFile(path) as archive:
        (entry,) = [e for e in archive.infolist() if e.filename.endswith(member_suffix)]
    raw = path.read_bytes()
    header = entry.header_offset
    return header + 30 + int.from_bytes(raw[header + 26:header + 28], "little") + int.from_bytes(raw[header + 28:header + 30], "little")


def flip_centre_byte(path: Path, at: int = 4 * 1536 + 2) -> None:
    data = bytearray(path.read_bytes())
    data[data_offset(path, "data/0") + at] ^= 0x10
    path.write_bytes(bytes(data))


def test_files_without_our_checksum_are_checked_by_their_zip_crcs(shared_data, tmp_path, cli):
    """torch.load does not check the CRC-32s its zip writer stores. Was: one flipped bit in the authors'
    c_centers.pt (placed in the cache, or given by path) or in a vocabulary saved before vocabularies
    carried a checksum loaded as it stood: every descriptor made with a damaged centre, no word."""
    earlier = tmp_path / "earlier.pt"
    torch.save({"centres": centres(), "meta": {"source": "indoor"}}, earlier)  # as saved before checksums
    released = tmp_path / "urban" / "c_centers.pt"
    released.parent.mkdir()
    shutil.copyfile(shared_data / RELEASED / "urban" / "c_centers.pt", released)
    whole = load_vocabulary(released).centres
    assert torch.equal(load_vocabulary(earlier).centres, centres()) and whole.shape == (32, 1536)
    for path in (earlier, released):
        flip_centre_byte(path)
        code, out, err = cli("vocabulary", "show", path)
        assert (code, out) == (1, "") and err == (
            f"error: Vocabulary file {path} is damaged: its bytes no longer match the CRC-32 written with them "
            f"(Bad CRC-32 for file '{path.stem}/data/0'). Delete it and fit, import or download it again (`vprbench "
            "vocabulary fit`, `import`, or `download` for the authors' released centres).\n")
    # a run naming the released vocabulary finds the damaged copy in the cache and refuses it too
    cache = tmp_path / "cache"
    target = cache / "vocabularies" / "dinov2_vitg14-l31-value-c32" / "urban" / "c_centers.pt"
    target.parent.mkdir(parents=True)
    shutil.copyfile(released, target)
    with pytest.raises(VPRBenchError, match=r"is damaged: its bytes no longer match the CRC-32"):
        resolve_vocabulary("urban", "dinov2_vitg14", 31, "value", 32, cache)
    # nothing to check (torch's CRC option off writes 0; the pre-zip format has none): loaded as before,
    # and half or double centres are taken as float32
    torch.save(centres(), tmp_path / "legacy.pt", _use_new_zipfile_serialization=False)
    torch.serialization.set_crc32_options(False)
    try:
        torch.save({"centres": centres(), "meta": {}}, tmp_path / "no_crc.pt")
    finally:
        torch.serialization.set_crc32_options(True)
    with zipfile.ZipFile(tmp_path / "no_crc.pt") as archive:
        assert any(e.CRC == 0 and e.file_size for e in archive.infolist())  # really written without
    torch.save(centres(torch.float16), tmp_path / "half.pt")
    torch.save(centres(torch.float64), tmp_path / "double.pt")
    for name in ("legacy", "no_crc", "half", "double"):
        expected = centres(torch.float16).float() if name == "half" else centres()
        assert torch.equal(load_vocabulary(tmp_path / f"{name}.pt").centres, expected), name


def test_show_and_list_say_what_was_learnt(shared_data, tmp_path, cli):
    """Was: `vocabulary show` of the authors' centres printed only their size and path, and there was no
    `vocabulary list` (argparse: invalid choice). Names from data (folders, metadata) print escaped."""
    cache = tmp_path / "cache"
    urban = shared_data / RELEASED / "urban" / "c_centers.pt"
    assert cli("vocabulary", "import", urban, "--source", "urban", "--cache-dir", cache)[0] == 0
    fitted = Vocabulary(torch.eye(4, 384), {"datasets": {"corridor": 111}, "features_used": 50, "features_seen": 88})
    save_to_cache(fitted, "dinov2_vits14@random", 2, "value", "map-corridor", cache)
    odd = Vocabulary(torch.eye(4, 384)).save(cache / "vocabularies" / "dinov2_vits14-l2-value-c4" / "odd\x1b[2Jname" / "vocabulary.pt")
    bare = tmp_path / "bare.pt"
    torch.save(centres(), bare)
    code, out, err = cli("vocabulary", "list", "--cache-dir", cache)
    assert (code, err) == (0, "")
    assert out.splitlines() == [
        f"Vocabularies in {cache / 'vocabularies'} (setting/name: clusters x dims, fitted on):",
        "  dinov2_vitg14-l31-value-c32/urban: 32 x 1536, the authors' released 'urban' centres "
        "(AnyLoc/Revisit-Anything at 89cade5529a5): dinov2_vitg14 layer 31 value features of oxford, st-lucia, pitts30k",
        "  dinov2_vits14-l2-value-c4/odd\\x1b[2Jname: 4 x 384, not recorded in the file (centres without metadata; "
        f"sha256 {file_sha256(odd)[:16]})",
        "  dinov2_vits14@random-l2-value-c4/map-corridor: 4 x 384, backbone dinov2_vits14@random layer 2 facet value "
        "features of corridor (111 images), 50 of 88 features sampled",
    ]
    code, out, _ = cli("vocabulary", "show", urban)
    assert code == 0 and out.splitlines()[1] == (
        "  fitted on: the authors' released 'urban' centres (AnyLoc/Revisit-Anything at 89cade5529a5): "
        "dinov2_vitg14 layer 31 value features of oxford, st-lucia, pitts30k")
    code, out, _ = cli("vocabulary", "show", bare)
    assert code == 0 and out.splitlines()[1].startswith("  fitted on: not recorded in the file (centres without metadata")
    assert cli("vocabulary", "list", "--cache-dir", tmp_path / "none")[1] == (
        f"No vocabularies in {tmp_path / 'none' / 'vocabularies'}: `vprbench vocabulary fit`, `import` or `download` makes them.\n")


def test_a_save_removes_what_a_killed_save_left(tmp_path):
    """Before: a fit killed while saving left `.vocabulary.pt.*.tmp` in the folder for good. A
    leftover untouched for an hour goes at the next save; a younger one (a live save) stays."""
    folder = tmp_path / "dinov2_vits14-l11-value-c4" / "mine"
    folder.mkdir(parents=True)
    old, young = folder / ".vocabulary.pt.killed.tmp", folder / ".vocabulary.pt.live.tmp"
    for leftover in (old, young):
        leftover.write_bytes(b"half a file")
    hours_ago = time.time() - 2 * 3600
    os.utime(old, (hours_ago, hours_ago))
    Vocabulary(torch.ones(4, 8), {"source": "mine"}).save(folder / "vocabulary.pt")
    assert sorted(p.name for p in folder.iterdir()) == [young.name, "vocabulary.pt"]
    assert load_vocabulary(folder / "vocabulary.pt").clusters == 4


def test_a_hand_made_files_metadata_reaches_a_record_cut(tmp_path):
    """What a file's metadata puts in a run's record (its folder, source, fitted stride, resize, image size)
    is kept as a fit writes it, and a hand-made file's megabyte-long value, or one of another type, as its
    text cut to one line's length: a record and the leaderboard's Weights cell stay readable."""
    from vprbench.methods.anyloc_provenance import file_provenance

    huge = "y" * 1_000_000
    Vocabulary(centres(), {"folder": huge, "source": huge, "resize": huge, "image_size": {"h": [0] * 10**5},
                           "stride": 4}).save(tmp_path / "huge.pt")
    found = file_provenance(load_vocabulary(tmp_path / "huge.pt"))
    assert len(str(found)) < 10_000 and found["fitted_stride"] == 4
    assert found["folder"].endswith("...") and isinstance(found["fitted_image_size"], str)
    Vocabulary(centres(), {"folder": "/data/mine", "resize": [56, 56], "image_size": "native"}).save(tmp_path / "fit.pt")
    found = file_provenance(load_vocabulary(tmp_path / "fit.pt"))
    assert (found["folder"], found["fitted_resize"], found["fitted_image_size"]) == ("/data/mine", [56, 56], "native")


def test_a_hand_made_files_setting_is_named_cut_in_its_refusal(tmp_path, cli):
    """A file whose metadata names other features is refused in one line of readable length, however long
    (and whatever characters) its hand-made setting."""
    Vocabulary(torch.randn(4, 384), {"backbone": "x\n\x1b[2J" * 10**5, "layer": 3}).save(tmp_path / "v.pt")
    code, out, err = cli("vocabulary", "import", tmp_path / "v.pt", "--source", "mine", "--backbone", "dino_vits8",
                         "--layer", "11", "--facet", "value", "--cache-dir", tmp_path / "cache")
    assert code == 1 and out == "" and len(err) < 1_000 and err.count("\n") == 1, err[:300]
    assert "was fitted on backbone x\\n\\x1b[2J" in err and "\x1b" not in err


def test_two_fits_of_one_vocabulary_at_once_leave_one_whole_file(shared_data, tmp_path, cli):
    """Two `vocabulary fit` runs of the same key on one cache, at the same time: both finish, and one whole
    vocabulary is cached (each save is atomic and they take turns), listed once."""
    cache = tmp_path / "cache"
    fit = [sys.executable, "-m", "vprbench", "vocabulary", "fit", "--method", "anyloc", "--backbone", "dinov2_vits14",
           "--weights", "random", "--layer", "0", "--clusters", "4", "--budget", "2000", "--dataset", "corridor",
           "--data-dir", str(shared_data), "--cache-dir", str(cache), "--quiet"]
    runs = [subprocess.Popen(fit, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    done = [(run.wait(timeout=600), *run.communicate()) for run in runs]
    folder = cache / "vocabularies" / "dinov2_vits14@random-l0-value-c4" / "map-corridor"
    for code, out, err in done:
        assert code == 0 and "Traceback" not in err, err
        assert out.strip() == f"Vocabulary map-corridor: 4 x 384, 2000 of 9768 features -> {folder / 'vocabulary.pt'}"
    assert sorted(p.name for p in folder.iterdir()) == [".vocabulary.pt.lock", "vocabulary.pt"]  # no temporaries
    assert load_vocabulary(folder / "vocabulary.pt").centres.shape == (4, 384)  # whole: its checksum holds
    code, out, err = cli("vocabulary", "list", "--cache-dir", cache)
    assert code == 0 and out.count("map-corridor: 4 x 384") == 1 and len(out.strip().splitlines()) == 2, out
    code, out, err = cli("vocabulary", "show", folder / "vocabulary.pt")
    assert code == 0 and "4 clusters x 384 dims" in out and "corridor (111 images)" in out, out
