import numpy as np
import pytest

from vprbench.errors import VPRBenchError
from vprbench.methods import create_method


@pytest.fixture
def corridor_images(shared_data):
    return sorted((shared_data / "corridor" / "ref").glob("*.jpg"))[:12]


def test_dense_vlad_fits_and_describes_independently_of_batches(corridor_images):
    method = create_method("dense-vlad", clusters=8, bin_sizes=(6,), step=6)
    method.fit(corridor_images[:8])
    assert method.centres.shape == (8, 128)
    together = method.describe(corridor_images[8:])
    alone = np.concatenate([method.describe([p]) for p in corridor_images[8:]])
    assert together.shape == (4, 8 * 128) and together.dtype == np.float32
    np.testing.assert_allclose(together, alone, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(together, axis=1), 1, rtol=1e-5)

    again = create_method("dense-vlad", clusters=8, bin_sizes=(6,), step=6)
    again.fit(corridor_images[:8])
    np.testing.assert_array_equal(again.centres, method.centres)  # seeded


def test_rootsift_rows_are_unit_length(corridor_images):
    features = create_method("dense-vlad", bin_sizes=(4,), step=8).local_features(corridor_images[0])
    assert features.shape[1] == 128 and (features >= 0).all()
    np.testing.assert_allclose(np.linalg.norm(features, axis=1), 1, rtol=1e-4)


def test_dense_vlad_needs_fit_and_enough_features(corridor_images):
    with pytest.raises(VPRBenchError, match="not fitted"):
        create_method("dense-vlad").describe(corridor_images[:1])
    with pytest.raises(VPRBenchError, match="option sample takes a whole number >= 128"):
        create_method("dense-vlad", sample=50)
    # 12 keypoints per image (bin 10, step 40 on 160x120): 24 descriptors for 128 words
    with pytest.raises(VPRBenchError, match="24 sampled descriptors cannot make 128 clusters"):
        create_method("dense-vlad", bin_sizes=(10,), step=40).fit(corridor_images[:2])


def test_hog_dimension_and_settings(corridor_images):
    descriptors = create_method("hog", resize=(64, 64)).describe(corridor_images[:2])
    # 64x64 window, 16px blocks every 8px: 7x7 blocks of one 16px cell, 9 bins
    assert descriptors.shape == (2, 7 * 7 * 9)
    with pytest.raises(VPRBenchError, match=r"multiple of block_stride \(8\)"):
        create_method("hog", resize=(60, 64))


def test_hog_says_once_when_it_upsamples_thumbnails(tmp_path, recwarn):
    """64 x 32 frames go to the protocol's 512 x 512 window (128 times their area): said once,
    with the --resize that keeps them near their size; that run says nothing."""
    from PIL import Image

    from vprbench.cli.main import main

    rng = np.random.default_rng(0)
    rows = ["image,frame"]
    for split in ("database", "queries"):
        (tmp_path / "thumbs" / split).mkdir(parents=True)
        for i in range(4):
            Image.fromarray(rng.integers(0, 255, (32, 64, 3), dtype=np.uint8)).save(tmp_path / "thumbs" / split / f"{i}.png")
            rows.append(f"{split}/{i}.png,{i}")
    (tmp_path / "thumbs" / "positions.csv").write_text("\n".join(rows) + "\n")
    (tmp_path / "thumbs" / "dataset.toml").write_text("radius = 1\n")
    args = ["evaluate", "--method", "hog", "--dataset", str(tmp_path / "thumbs"), "--k", "1", "--quiet"]
    assert main(args) == 0
    said = [str(w.message) for w in recwarn if "resized to its" in str(w.message)]
    assert len(said) == 1 and said[0].startswith("hog: the images of thumbs (64 x 32) are resized to its 512 x 512")
    assert "128 times their area, 35,721 dimensions a descriptor (143 kB in float32)" in said[0] and "--resize 32 64" in said[0]
    recwarn.clear()
    assert main(args + ["--resize", "32", "64"]) == 0
    assert not [w for w in recwarn if "resized to its" in str(w.message)]
