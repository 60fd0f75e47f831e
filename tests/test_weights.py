"""Weight files are read without running code, and a bad one is named."""
import pytest
import torch

from vprbench.errors import VPRBenchError
from vprbench.weights import file_sha256, read_torch_file


@pytest.mark.parametrize("content", [b"junk", b"PK\x03\x04 truncated zip", b"\x80\x02}q\x00(X\x01"])
def test_unreadable_weight_files_are_named(tmp_path, content):
    path = tmp_path / "w.pth"
    path.write_bytes(content)
    with pytest.raises(VPRBenchError, match=r"Cannot read weights file .*w\.pth: it is damaged or not a PyTorch file"):
        read_torch_file(path, "weights file")


def test_pickled_objects_are_refused_with_a_way_out(tmp_path):
    path = tmp_path / "ckpt.pth"
    torch.save({"state_dict": {"w": torch.ones(2)}, "args": tmp_path}, path)  # a PosixPath is code to unpickle
    with pytest.raises(VPRBenchError, match="also holds Python objects .*save its weights alone"):
        read_torch_file(path)


def test_numpy_scores_beside_weights_load_and_hash_is_stable(tmp_path):
    import numpy as np

    path = tmp_path / "ok.pth"
    torch.save({"state_dict": {"w": torch.ones(2)}, "best_score": np.float64(0.9)}, path)
    assert read_torch_file(path)["best_score"] == 0.9
    assert file_sha256(path) == file_sha256(path) and len(file_sha256(path)) == 64
