""".npz files from elsewhere (backbone weights, a saved post-processing state) go through the one
guarded reader (datasets/layouts/npy.py: read_npz, npz_headers): a member whose header claims more
than the file holds, members that unpack to more than such a file may hold (a compression bomb), a
shape no array has, a torn zip, no zip at all, Python objects, and shapes that fit nothing are one
line naming the file and what to do, never a traceback or an allocation of what a header claims."""
from __future__ import annotations

import io
import math
import struct
import zipfile
from pathlib import Path

import numpy as np
import torch
import pytest
from numpy.lib import format as npy_format

from vprbench import VPRBenchError
from vprbench.aggregation import PCAWhitening
from vprbench.datasets.layouts.npy import npz_headers, read_npz
from vprbench.evaluation.postprocess import fit_postprocessor
from vprbench.evaluation.record import per_query_arrays_in
from vprbench.row_sources import ArrayRows

#: a header's claim: 8 TB of float64, in a member of a few bytes
HUGE = (10**12,)
#: what a deflated bomb of 2 GiB of zeros (a 2 MB file) declares, in its header and in the zip
#: directory alike, forged here in a few bytes
BOMB = (2**28,)


def npy_bytes(array: np.ndarray) -> bytes:
    out = io.BytesIO()
    np.save(out, array, allow_pickle=True)
    return out.getvalue()


def claiming(shape, dtype="<f8") -> bytes:
    """A .npy member whose header announces `shape`, followed by 16 data bytes."""
    out = io.BytesIO()
    npy_format.write_array_header_1_0(out, {"descr": dtype, "fortran_order": False, "shape": shape})
    return out.getvalue() + bytes(16)


def npz(path: Path, members: dict[str, bytes]) -> Path:
    """An .npz of raw members (name -> .npy bytes), as np.savez lays them out."""
    with zipfile.ZipFile(path, "w") as archive:
        for name, data in members.items():
            archive.writestr(f"{name}.npy", data)
    return path


def unpacked_size(path: Path, member: str, size: int) -> None:
    """The uncompressed size the zip directory of `path` gives `member`, set to `size`."""
    data = bytearray(path.read_bytes())
    at = data.index(b"PK\x01\x02")  # the central directory's first entry
    while True:
        length = struct.unpack_from("<H", data, at + 28)[0]
        if data[at + 46:at + 46 + length].decode() == member:
            struct.pack_into("<I", data, at + 24, size)
            return path.write_bytes(bytes(data))
        extra, comment = struct.unpack_from("<HH", data, at + 30)
        at += 46 + length + extra + comment


def hostile(kind: str, path: Path, arrays: dict[str, np.ndarray], target: str) -> Path:
    """`arrays` saved at `path`, spoilt as `kind` says (`target`: the member spoilt)."""
    members = {name: npy_bytes(value) for name, value in arrays.items()}
    if kind == "huge header":
        members[target] = claiming(HUGE)
    elif kind == "bomb":
        members[target] = claiming(BOMB)
    elif kind == "negative dimension":  # 16 x -1 x 16 x 3 values: fewer than none, so no more than it holds
        members[target] = claiming((16, -1, 16, 3))
    elif kind == "objects":
        members[target] = npy_bytes(np.array([1, "two", None], dtype=object))
    elif kind == "texts":
        members[target] = npy_bytes(np.array(["not", "numbers"]))
    npz(path, members)
    if kind == "bomb":
        unpacked_size(path, f"{target}.npy", len(members[target]) - 16 + 8 * math.prod(BOMB))
    if kind == "truncated zip":
        path.write_bytes(path.read_bytes()[:-60])  # its central directory cut off
    elif kind == "no zip":  # a bare .npy under the .npz name: numpy would hand back an array
        path.write_bytes(npy_bytes(next(iter(arrays.values()))))
    return path


#: each hostile kind and what the one line says of it
SAID = {"huge header": "is truncated (16 of 8000000000000 data bytes)",
        "bomb": "it unpacks to 2.1 GB, more than the 1.1 GB such a file may hold (a compression bomb, or not such a file)",
        "negative dimension": "its header announces shape (16, -1, 16, 3), which no array has",
        "objects": "holds object values (Python objects, which are never loaded)",
        "truncated zip": "it is not a complete .npz archive",
        "no zip": "it is not a complete .npz archive"}


@pytest.fixture(autouse=True)
def unread_claims(monkeypatch):
    """Fails a test in which numpy reads an array of more than 1 MB (what a hostile header claims),
    before it allocates it."""
    real = npy_format.read_array

    def read_array(handle, *args, **kwargs):
        start = handle.tell()
        version = npy_format.read_magic(handle)
        shape, _, dtype = (npy_format.read_array_header_1_0 if version == (1, 0) else
                           npy_format.read_array_header_2_0)(handle)
        handle.seek(start)
        if abs(math.prod(shape)) * dtype.itemsize > 2**20:
            pytest.fail(f"numpy was asked to read an array of shape {shape}")
        return real(handle, *args, **kwargs)

    monkeypatch.setattr(npy_format, "read_array", read_array)


# ---------------------------------------------------------------- the reader itself
@pytest.mark.parametrize("kind", sorted(SAID))
@pytest.mark.parametrize("read", [read_npz, npz_headers])
def test_the_reader_refuses_each_hostile_archive_in_one_line(kind, read, tmp_path):
    path = hostile(kind, tmp_path / "x.npz", {"a": np.arange(4.0), "b": np.ones((2, 2))}, "b")
    with pytest.raises(VPRBenchError) as caught:
        read(path, "test file", "two arrays; write it again")
    message = str(caught.value)
    assert message.startswith(f"Cannot read test file {path}: ") and message.endswith("Expected two arrays; write it again.")
    assert SAID[kind] in message and "\n" not in message and "allow_pickle" not in message
    if kind in ("huge header", "bomb", "negative dimension", "objects"):
        assert "its member b.npy: " in message


def test_a_deflated_bomb_is_refused_before_any_member_is_unpacked(tmp_path, monkeypatch):
    """Zeros deflate to a thousandth (a gigabyte in a megabyte): here 4 MB in a few kB, under a
    bound of 1 MiB its caller gives; the zip directory's sizes are checked before a member is opened."""
    np.savez_compressed(tmp_path / "one.npz", a=np.zeros(2**22, np.uint8))
    np.savez_compressed(tmp_path / "two.npz", a=np.zeros(600_000, np.uint8), b=np.zeros(600_000, np.uint8))
    assert (tmp_path / "one.npz").stat().st_size < 2**15
    monkeypatch.setattr(zipfile.ZipFile, "open", lambda *args, **kwargs: pytest.fail("a member was opened"))
    for read in (read_npz, npz_headers):
        with pytest.raises(VPRBenchError) as caught:
            read(tmp_path / "one.npz", "test file", "arrays", max_bytes=2**20)
        assert str(caught.value) == (f"Cannot read test file {tmp_path / 'one.npz'}: its member a.npy: it unpacks to "
                                     "4.2 MB, more than the 1.0 MB such a file may hold (a compression bomb, or not "
                                     "such a file). Expected arrays.")
        with pytest.raises(VPRBenchError, match=r"its member b\.npy: it unpacks to 600\.1 kB \(1\.2 MB with the "
                                                r"members before it\), more than the 1\.0 MB"):
            read(tmp_path / "two.npz", "test file", "arrays", max_bytes=2**20)


def test_per_query_arrays_of_a_bomb_are_refused_unread(tmp_path):
    path = hostile("bomb", tmp_path / "run.npz", {"database_indices": np.zeros((3, 2), np.int64),
                                                  "similarities": np.zeros((3, 2), np.float32)}, "similarities")
    with pytest.raises(ValueError, match=f"its member similarities.npy: {SAID['bomb']}".replace("(", r"\(")
                       .replace(")", r"\)").replace(".", r"\.")):
        per_query_arrays_in(path.read_bytes())


def test_the_reader_reads_what_numpy_saves(tmp_path):
    np.savez(tmp_path / "plain.npz", a=np.arange(3), key=np.array("text"))
    np.savez_compressed(tmp_path / "packed.npz", a=np.arange(3), key=np.array("text"))
    for name in ("plain.npz", "packed.npz"):
        found = read_npz(tmp_path / name, "test file", "arrays")
        assert sorted(found) == ["a", "key"] and found["a"].tolist() == [0, 1, 2] and str(found["key"]) == "text"
        assert npz_headers(tmp_path / name, "test file", "arrays")["a"] == ((3,), found["a"].dtype)
    with pytest.raises(VPRBenchError, match="its member key.npy: it holds <U4 values"):
        read_npz(tmp_path / "plain.npz", "test file", "numbers", kinds="iuf")


# ---------------------------------------------------------------- a saved PCA state
def saved_state(tmp_path) -> tuple[ArrayRows, dict, dict[str, np.ndarray]]:
    """Rows, the info of their fitted PCA state, and the arrays saved in it."""
    rows = ArrayRows(np.random.default_rng(0).standard_normal((64, 16)).astype(np.float32), folder=tmp_path)
    info = fit_postprocessor(PCAWhitening(8), rows, 2**28)
    with np.load(info["file"]) as saved:
        return rows, info, {name: saved[name] for name in saved.files}


STATES = {**SAID,
          "state of another width": "it is unusable for these 16-dimensional descriptors (PCA was fitted on "
                                    "12-dimensional descriptors, got shape (1, 16): fit it on descriptors of this "
                                    "method, or load the state fitted on them)",
          "mean of another width": "it is unusable (Saved PCA state has a mean of shape (5,) for a projection of shape (8, 16)",
          "projection of no matrix": "it is unusable (Saved PCA state has a projection of shape (128,), expected (8, D)"}


@pytest.mark.parametrize("kind", sorted(STATES))
def test_a_hostile_post_processing_state_is_named_and_fitted_again(kind, tmp_path):
    rows, info, arrays = saved_state(tmp_path)
    path = Path(info["file"])
    if kind == "mean of another width":
        arrays["pca_mean"] = arrays["pca_mean"][:5]
    if kind == "projection of no matrix":
        arrays["pca_projection"] = arrays["pca_projection"].reshape(-1)
    if kind == "state of another width":  # consistent in itself, under this run's key: fitted on other rows
        arrays["pca_projection"], arrays["pca_mean"] = arrays["pca_projection"][:, :12], arrays["pca_mean"][:12]
    hostile(kind, path, arrays, "pca_mean")
    pca = PCAWhitening(8)
    with pytest.warns(UserWarning) as caught:
        assert fit_postprocessor(pca, rows, 2**28)["state"] == "fitted"
    message = str(caught[0].message).replace(f"the post-processing state {path} is unusable", "it is unusable")
    assert str(caught[0].message).startswith("Refitting: ") and str(path) in str(caught[0].message), caught[0].message
    assert STATES[kind] in message and "\n" not in message, message
    fresh = PCAWhitening(8).fit(rows)
    np.testing.assert_allclose(pca.transform(rows.read_rows(0, 64)), fresh.transform(rows.read_rows(0, 64)), atol=1e-5)
    assert fit_postprocessor(PCAWhitening(8), rows, 2**28)["state"] == "loaded"  # the file was replaced


def test_a_state_bigger_than_the_default_bound_is_bounded_by_its_rows(tmp_path, monkeypatch):
    """A PCA state of wide VLAD rows may exceed the reader's default bound (196,608 dims to 4,096:
    3 GB): a (D x D) matrix or the rows themselves, in float64, bound it then, whatever the memory
    budget of the run that loads it (was: that budget, so a run with less memory refitted a sound state)."""
    from vprbench.datasets.layouts import npy
    from vprbench.evaluation.postprocess import _load_state

    rows, info, _ = saved_state(tmp_path)
    size = sum(zipfile.ZipFile(info["file"]).getinfo(n).file_size for n in zipfile.ZipFile(info["file"]).namelist())
    monkeypatch.setattr(npy, "NPZ_MAX_BYTES", size - 1)
    assert 8 * 16 * (64 + 1) > size  # 64 rows of 16 dims bound it
    assert fit_postprocessor(PCAWhitening(8), rows, 2**28)["state"] == "loaded"
    with np.load(info["file"]) as saved:
        key = str(saved["key"])
    assert _load_state(PCAWhitening(8), Path(info["file"]), key, 16, 64) is None
    assert "compression bomb" in _load_state(PCAWhitening(8), Path(info["file"]), key, 1, 1)  # beyond both bounds


# ---------------------------------------------------------------- .npz weights
@pytest.fixture
def siglip(monkeypatch):
    """A tiny SigLIP 2 entry and its big_vision arrays."""
    from release_formats import siglip2_npz

    from vprbench.features.backbones import create_model
    from vprbench.features.catalogue import backbone_spec, backbones

    entry = backbone_spec("siglip2_b16")
    size = {"depth": 2, "embed_dim": 96, "num_heads": 2}
    spec = entry.model_copy(update={"name": "tiny-siglip2_b16", "depth": 2, "width": 96,
                                    "timm_kwargs": {**entry.timm_kwargs, **size}})
    monkeypatch.setitem(backbones(), spec.name, spec)
    return spec, siglip2_npz(create_model(spec))


WEIGHTS = {**SAID, "texts": "its member params/img/embedding/kernel.npy: it holds <U7 values",
           # nothing is unpacked when the headers are read: what timm would read is bounded by the model
           "bomb": "params/img/embedding/kernel: file (268435456,) holds more values than any parameter of the model"}


@pytest.mark.parametrize("kind", sorted(WEIGHTS))
def test_hostile_npz_weights_are_named_with_what_to_do(kind, siglip, tmp_path):
    from vprbench.features.backbones import load_backbone

    spec, arrays = siglip
    path = hostile(kind, tmp_path / "release.npz", arrays, "params/img/embedding/kernel")
    with pytest.raises(VPRBenchError) as caught:
        load_backbone(spec.name, path)
    message = str(caught.value)
    assert message.startswith(f"{path} for backbone {spec.name}: The weights file does not fit" if kind == "bomb"
                              else f"Backbone {spec.name}: Cannot read weights file {path}: "), message
    assert WEIGHTS[kind] in message and "\n" not in message, message
    assert ("Pass a checkpoint of this backbone" if kind == "bomb" else
            "pass the release file as published (download it again), or another.") in message


@pytest.mark.parametrize("member, shape, said", [
    ("params/img/embedding/kernel", (10**4, 10**4, 0, 10**4, 10**4),
     "patch_embed.proj.weight: file (10000, 10000, 10000, 10000)"),  # its dimension of 0 is not among the four kept
    ("params/img/pos_embedding", (96,), "pos_embed: file (96,) vs model (1, 196, 96)")])
def test_npz_weights_of_shapes_that_fit_nothing_are_a_misfit(member, shape, said, siglip, tmp_path):
    """Shapes of no data (a dimension of 0) or too few dimensions: compared, never allocated."""
    from vprbench.features.backbones import load_backbone

    spec, arrays = siglip
    arrays[member] = np.zeros(shape, np.float32)
    np.savez(tmp_path / "release.npz", **arrays)
    with pytest.raises(VPRBenchError, match="does not fit this backbone") as caught:
        load_backbone(spec.name, tmp_path / "release.npz")
    assert said in str(caught.value)


def test_a_classifier_head_the_model_has_no_layer_for_is_never_read(siglip, tmp_path):
    """A release with an in21k classifier (width x 21843, more values than any parameter of a model
    without a head) loads: timm never reads a head the model has no linear layer for (and the
    autouse check fails the test if numpy is asked to read it). Was: refused as a misfit."""
    from vprbench.features.backbones import load_backbone

    spec, arrays = siglip
    np.savez(tmp_path / "release.npz", **arrays, **{"params/img/head/kernel": np.zeros((96, 21843), np.float32),
                                                     "params/img/head/bias": np.zeros(21843, np.float32)})
    model, _, identity = load_backbone(spec.name, tmp_path / "release.npz")
    assert identity.startswith("sha256:") and all(torch.isfinite(p).all() for p in model.parameters())
