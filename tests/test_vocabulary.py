import numpy as np
import pytest
import torch
import torch.nn.functional as F

from vprbench.aggregation import FeatureSampler, Vocabulary, fit_vocabulary, kmeans_cosine, load_vocabulary, vlad_hard
from vprbench.methods.anyloc_fit import fit_domain_vocabulary
from vprbench.methods.anyloc_lookup import resolve_vocabulary
from vprbench.methods.anyloc_vocabulary import domain_datasets, paper_vocabulary, save_to_cache
from vprbench.errors import VPRBenchError

RELEASED = "vocabularies/anyloc-dinov2_vitg14-l31-value-c32"


def features(n=300, d=8, seed=0):
    return F.normalize(torch.randn(n, d, generator=torch.Generator().manual_seed(seed)), dim=-1)


def test_kmeans_is_deterministic_and_seeded():
    x = features()
    a, iterations = kmeans_cosine(x, 6, seed=42)
    b, _ = kmeans_cosine(x.numpy(), 6, seed=42)
    assert torch.equal(a, b) and 1 <= iterations <= 100
    c, _ = kmeans_cosine(x, 6, seed=7)
    assert not torch.equal(a, c)
    # centres are plain means, so not unit vectors
    assert (a.norm(dim=1) < 0.999).all()


def test_kmeans_initial_centres_are_the_numpy_seed_draw():
    x = features(50)
    start = np.random.RandomState(42).choice(50, size=[4], replace=False)
    centres, iterations = kmeans_cosine(x, 4, seed=42, max_iter=1)
    labels = (F.normalize(x) @ F.normalize(x[start]).T).argmax(1)
    assert iterations == 1
    assert torch.allclose(centres[0], x[labels == 0].mean(0), atol=1e-6)


def test_kmeans_empty_cluster_becomes_zero():
    # three identical rows and one other: a third centre drawn on a duplicate gets no member
    x = torch.tensor([[1.0, 0.0], [1.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    centres, _ = kmeans_cosine(x, 3, seed=42)
    assert sorted(map(tuple, centres.tolist())) == [(0.0, 0.0), (0.0, 1.0), (1.0, 0.0)]


def test_more_clusters_than_features_is_a_clear_error():
    with pytest.raises(VPRBenchError, match="Cannot fit 10 clusters on 4 features"):
        kmeans_cosine(features(4), 10)
    with pytest.raises(VPRBenchError, match="Cannot fit 10 clusters on 6 features"):
        fit_vocabulary([features(3), features(3, seed=1)], 10)


def test_sampler_buffer_never_exceeds_budget():
    sampler = FeatureSampler(budget=100, seed=1)
    for i in range(40):
        sampler.add(features(37, seed=i))
        assert sampler.buffer.shape == (100, 8)
        assert len(sampler.sample()) == min(sampler.seen, 100)
    assert sampler.seen == 40 * 37
    assert np.allclose(np.linalg.norm(sampler.sample(), axis=1), 1, atol=1e-6)


def test_sampler_is_seeded_and_roughly_uniform():
    # image i's 10 features point at angle 0.005 * i, so a sampled row tells its image
    angles = 0.005 * torch.arange(200.0)
    stream = [torch.stack([angle.cos(), angle.sin()]).repeat(10, 1) for angle in angles]

    def run(seed):
        sampler = FeatureSampler(budget=400, seed=seed)
        for chunk in stream:
            sampler.add(chunk)
        return sampler.sample().copy()

    a, b = run(5), run(5)
    assert np.array_equal(a, b) and not np.array_equal(a, run(6))
    index = np.round(np.arctan2(a[:, 1], a[:, 0]) / 0.005).astype(int)
    # a uniform sample of 400 out of 2000: mean image index ~99.5 (sd ~2.6), every part of the stream present
    assert len(a) == 400 and 90 < index.mean() < 109
    assert index.min() < 10 and index.max() > 190


def test_sampler_errors():
    with pytest.raises(VPRBenchError, match="budget"):
        FeatureSampler(budget=0)
    sampler = FeatureSampler(budget=5)
    with pytest.raises(VPRBenchError, match="No features"):
        sampler.sample()
    sampler.add(features(3))
    with pytest.raises(VPRBenchError, match="dimension changed from 8 to 4"):
        sampler.add(features(3, d=4))


def test_fit_vocabulary_exact_equals_kmeans_on_all_and_sampled_is_bounded():
    stream = [features(50, seed=i) * 3 for i in range(6)]  # unnormalised in, normalised inside
    exact = fit_vocabulary(stream, 5, exact=True)
    assert torch.equal(exact.centres, kmeans_cosine(F.normalize(torch.cat(stream)), 5)[0])
    sampled = fit_vocabulary(iter(stream), 5, budget=120, meta={"backbone": "x"})
    assert sampled.meta["features_used"] == 120 and sampled.meta["features_seen"] == 300
    assert sampled.meta["backbone"] == "x" and sampled.clusters == 5 and sampled.dim == 8


def test_save_load_roundtrip_and_cache(tmp_path):
    vocabulary = Vocabulary(torch.randn(4, 8), {"backbone": "dinov2_vits14", "layer": 11})
    loaded = load_vocabulary(vocabulary.save(tmp_path / "v.pt"))
    assert torch.equal(loaded.centres, vocabulary.centres) and loaded.meta["layer"] == 11
    np.save(tmp_path / "c.npy", vocabulary.centres.numpy())
    assert torch.equal(load_vocabulary(tmp_path / "c.npy").centres, vocabulary.centres)
    save_to_cache(vocabulary, "dinov2_vits14", 11, "value", "indoor")
    found = resolve_vocabulary("indoor", "dinov2_vits14", 11, "value", 4)
    assert torch.equal(found.centres, vocabulary.centres) and found.meta["source"] == "indoor"
    with pytest.raises(VPRBenchError, match="has 4 clusters, the method asks for 8"):
        resolve_vocabulary(str(tmp_path / "v.pt"), "dinov2_vits14", 11, "value", 8)
    with pytest.raises(VPRBenchError, match="No 'indoor' vocabulary .* 8 clusters"):
        resolve_vocabulary("indoor", "dinov2_vits14", 11, "value", 8)
    with pytest.raises(VPRBenchError, match="vocabulary fit --dataset baidu-mall --method anyloc --backbone dinov2_vits14"):
        resolve_vocabulary("map-baidu-mall", "dinov2_vits14", 11, "value", 4)


def test_a_vocabulary_killed_while_saving_leaves_the_cached_one_whole(tmp_path):
    """kill -9 halfway through writing the file: the vocabulary cached before stays, whole."""
    import signal
    import subprocess
    import sys

    from vprbench.fsutil import is_temporary

    path = tmp_path / "vocabulary.pt"
    Vocabulary(torch.ones(2, 3), {"source": "before"}).save(path)
    script = """
import os, pathlib, signal, sys, torch
from vprbench.aggregation import Vocabulary
def half_then_killed(target, data):
    with open(target, "wb") as f:
        f.write(data[:len(data) // 2])
        f.flush()
    os.kill(os.getpid(), signal.SIGKILL)
pathlib.Path.write_bytes = half_then_killed
Vocabulary(torch.zeros(2, 3), {"source": "after"}).save(sys.argv[1])
"""
    done = subprocess.run([sys.executable, "-c", script, str(path)], capture_output=True)
    assert done.returncode == -signal.SIGKILL
    found = load_vocabulary(path)
    assert found.meta["source"] == "before" and torch.equal(found.centres, torch.ones(2, 3))
    assert all(is_temporary(p) for p in tmp_path.iterdir() if p != path)  # at most the killed writer's leftover


def test_load_errors(tmp_path):
    with pytest.raises(VPRBenchError, match="does not exist"):
        load_vocabulary(tmp_path / "missing.pt")
    with pytest.raises(VPRBenchError, match="neither vocabulary.pt nor c_centers.pt"):
        load_vocabulary(tmp_path)
    (tmp_path / "bad.pt").write_text("not torch")
    with pytest.raises(VPRBenchError, match=r"Cannot read vocabulary file .*bad.pt: it is damaged or not a PyTorch "
                                            r"file.*copy it again, or fit it again \(`vprbench vocabulary fit`\)"):
        load_vocabulary(tmp_path / "bad.pt")
    torch.save(torch.zeros(5), tmp_path / "flat.pt")
    with pytest.raises(VPRBenchError, match=r"shape \(5,\)"):
        load_vocabulary(tmp_path / "flat.pt")


def test_released_centres_load_and_wrong_dimension(shared_data):
    path = shared_data / RELEASED / "indoor" / "c_centers.pt"
    if not path.is_file():
        pytest.skip(f"released centres {path} are absent")
    vocabulary = load_vocabulary(path.parent)  # the folder works too
    assert vocabulary.centres.shape == (32, 1536) and vocabulary.centres.dtype == torch.float32
    vocabulary.check_dim(1536)
    with pytest.raises(VPRBenchError, match="1536-dimensional centres but the features are 384-dimensional"):
        vocabulary.check_dim(384)
    with pytest.raises(VPRBenchError, match="Vocabulary dimension 1536 does not match feature dimension 384"):
        vlad_hard(torch.randn(10, 384), vocabulary.centres)
    out = vlad_hard(F.normalize(torch.randn(20, 1536)), vocabulary.centres)
    assert out.shape == (32 * 1536,) and abs(out.norm().item() - 1) < 1e-5


def test_released_folder_copied_into_cache_is_found(shared_data, tmp_path):
    source = shared_data / RELEASED / "laurel_caverns" / "c_centers.pt"
    if not source.is_file():
        pytest.skip(f"released centres {source} are absent")
    from vprbench.aggregation.vocabulary import vocabulary_dir

    target = vocabulary_dir("dinov2_vitg14", 31, "value", 32, "laurel_caverns")
    target.mkdir(parents=True)
    (target / "c_centers.pt").write_bytes(source.read_bytes())
    found = resolve_vocabulary("laurel-caverns", "dinov2_vitg14", 31, "value", 32)
    assert found.centres.shape == (32, 1536)


def test_domain_policies():
    assert domain_datasets("indoor") == [("gardens-point", 1), ("17places", 1), ("baidu-mall", 1)]
    assert ("pitts30k", 4) in domain_datasets("urban") and ("vp-air", 2) in domain_datasets("aerial")
    assert len(domain_datasets("global")) == 12
    assert {name for name, _ in domain_datasets("unstructured")} == {
        "nardo-air", "nardo-air-r", "vp-air", "hawkins", "laurel-caverns", "mid-atlantic-ridge"}
    assert domain_datasets("structured")[0] == ("oxford", 1)  # the authors' concatenation order
    assert paper_vocabulary("baidu-mall") == "indoor"
    assert paper_vocabulary("mid-atlantic-ridge") == "map-mid-atlantic-ridge"
    with pytest.raises(VPRBenchError, match="Did you mean: indoor"):
        domain_datasets("indor")


def test_domain_fit_lists_every_missing_dataset(tmp_path):
    calls = []
    with pytest.raises(VPRBenchError) as info:
        fit_domain_vocabulary("indoor", lambda paths: calls.append(paths), 4, data_dir=tmp_path)
    message = str(info.value)
    assert all(name in message for name in ("gardens-point", "17places", "baidu-mall"))
    assert "c_centers.pt" in message and calls == []


def test_domain_fit_order_strides_and_metadata(monkeypatch):
    from types import SimpleNamespace

    import vprbench.datasets as datasets

    from pathlib import Path

    databases = {name: [Path(f"{name}/{i:03d}.jpg") for i in range(9)] for name, _ in domain_datasets("urban")}
    monkeypatch.setattr(datasets, "load_dataset", lambda name, data_dir=None, fetch=True, cache_dir=None: SimpleNamespace(name=name, database=databases[name]))
    seen = []

    def extract(paths):
        for path in paths:
            seen.append(path)
            yield features(20, seed=len(seen))

    vocabulary = fit_domain_vocabulary("urban", extract, 4, budget=50, meta={"backbone": "b"})
    # oxford and st-lucia every image, pitts30k every 4th, in the authors' order
    assert seen == databases["oxford"] + databases["st-lucia"] + databases["pitts30k"][::4]
    assert vocabulary.meta["datasets"] == {"oxford": 9, "st-lucia": 9, "pitts30k": 3}
    assert vocabulary.meta["image_size"] == [320, 320] and vocabulary.meta["source"] == "urban"
    assert vocabulary.meta["features_seen"] == 21 * 20 and vocabulary.meta["features_used"] == 50


def test_vocabulary_images_leave_out_distractors_and_stride():
    from pathlib import Path

    from vprbench.methods.anyloc_vocabulary import vocabulary_images

    refs = [Path(f"VPAir/reference_views/{i:05d}.png") for i in range(6)]
    distractors = [Path(f"VPAir/distractors/{i:05d}.png") for i in range(4)]
    assert vocabulary_images("vp-air", refs + distractors) == refs[::2]
    assert vocabulary_images("vp-air", refs + distractors, stride=1) == refs
    assert vocabulary_images("baidu-mall", refs + distractors) == refs + distractors


def test_kmeans_returns_the_update_that_met_the_tolerance():
    """The update is applied before the stop test: with any tolerance met at once, the centres
    are the means of the first assignment, not the initial rows."""
    x = torch.tensor([[1.0, 0.0], [0.8, 0.6], [0.0, 1.0], [-0.6, 0.8]])
    init = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    centres, iterations = kmeans_cosine(x, 2, init=init, tol=1e9)
    assert iterations == 1
    torch.testing.assert_close(centres, torch.tensor([[0.9, 0.3], [-0.3, 0.9]]))


def test_the_vocabulary_seed_reaches_the_kmeans_draw():
    features = [np.random.default_rng(i).normal(size=(40, 8)).astype(np.float32) for i in range(3)]
    fitted = fit_vocabulary(features, 4, exact=True, seed=7)
    expected, _ = kmeans_cosine(F.normalize(torch.from_numpy(np.concatenate(features)), dim=-1), 4, seed=7)
    torch.testing.assert_close(fitted.centres, expected)
    assert fitted.meta["seed"] == 7
    assert not torch.equal(fit_vocabulary(features, 4, exact=True, seed=42).centres, fitted.centres)


def test_the_sampler_is_a_sequential_reservoir():
    """Item t replaces slot j ~ U{0..t} when j < budget, items in stream order (a later item in the same
    slot wins): the batched sampler keeps what one-at-a-time reservoir sampling with its draws keeps."""
    stream = [np.eye(80, dtype=np.float32)[:50], np.eye(80, dtype=np.float32)[50:]]
    sampler = FeatureSampler(budget=5, seed=3)
    for chunk in stream:
        sampler.add(chunk)
    rng, kept, t = np.random.default_rng(3), list(range(5)), 5
    for stop in (50, 80):
        draws = rng.integers(0, np.arange(t, stop) + 1)
        for item, slot in zip(range(t, stop), draws):
            if slot < 5:
                kept[slot] = item
        t = stop
    assert np.argmax(sampler.sample(), axis=1).tolist() == kept
    assert len(set(kept)) == 5 and max(kept) >= 50  # the second chunk took part
