"""dense-vlad's `vocabulary` option: the evaluated database, a folder, a file, a dataset; provenance."""
import numpy as np
import pytest
import torch

from vprbench.aggregation import Vocabulary
from vprbench.errors import VPRBenchError
from vprbench.evaluation.provenance import method_provenance
from vprbench.methods import create_method

SMALL = {"clusters": 8, "bin_sizes": (6,), "step": 8}


@pytest.fixture
def corridor_refs(shared_data):
    return sorted((shared_data / "corridor" / "ref").glob("*.jpg"))


@pytest.fixture
def foreign_images(shared_data):
    folder = shared_data / "images" / "tokyo247-pair"
    if not folder.is_dir():
        pytest.skip(f"{folder} is absent")
    return folder


def test_map_vocabulary_is_marked_transductive(corridor_refs):
    method = create_method("dense-vlad", **SMALL)
    method.use_dataset("corridor")
    method.fit(corridor_refs[:6])
    found = method_provenance(method)
    assert found["weights"] == {"source": "none"}
    assert found["learnt"] == ["vocabulary"] and found["fitted_on_evaluated_database"] is True
    assert found["vocabulary"]["fitted_on"] == "the database of corridor"
    assert "vocabulary" not in method.fingerprint()  # stores of the map vocabulary keep their key


def test_folder_vocabulary_is_fitted_once_cached_and_identified_by_its_centres(foreign_images, corridor_refs, tmp_path):
    method = create_method("dense-vlad", vocabulary=str(foreign_images), cache_dir=tmp_path, **SMALL)
    method.use_dataset("corridor")
    assert not method.needs_fit
    described = method.describe([method.load(p) for p in corridor_refs[:2]])
    assert described.shape == (2, 8 * 128)
    np.testing.assert_allclose(np.linalg.norm(described, axis=1), 1, rtol=1e-5)
    cached = list((tmp_path / "vocabularies" / "dense-vlad").glob("tokyo247-pair-*/vocabulary.pt"))
    assert len(cached) == 1
    again = create_method("dense-vlad", vocabulary=str(foreign_images), cache_dir=tmp_path, **SMALL)
    again.fit_centres = None  # read from the cache: fitting again would fail
    assert again.fingerprint() == method.fingerprint()
    assert method.fingerprint()["vocabulary"] == "sha256:" + method.provenance()["vocabulary"]["centres_sha256"]
    found = method_provenance(method)
    assert found["fitted_on_evaluated_database"] is False and found["learnt"] == ["vocabulary"]
    assert found["vocabulary"]["fitted_on"].startswith(f"2 images in {foreign_images}")
    # another seed fits other words: another cache entry and another store key
    other = create_method("dense-vlad", vocabulary=str(foreign_images), cache_dir=tmp_path, seed=1, **SMALL)
    assert other.fingerprint()["vocabulary"] != method.fingerprint()["vocabulary"]


def test_a_damaged_cached_vocabulary_is_fitted_again_and_said(foreign_images, tmp_path):
    """Was: refused with "Delete it and fit it again", the file in the cache left to the user."""
    method = create_method("dense-vlad", vocabulary=str(foreign_images), cache_dir=tmp_path, **SMALL)
    first = method.fingerprint()["vocabulary"]
    cached = next((tmp_path / "vocabularies" / "dense-vlad").glob("tokyo247-pair-*/vocabulary.pt"))
    data = bytearray(cached.read_bytes())
    centres = torch.load(cached)["centres"].numpy().tobytes()
    data[bytes(data).index(centres[:64]) + 41] ^= 1  # one flipped bit in the centres
    cached.write_bytes(bytes(data))
    with pytest.warns(UserWarning, match=f"The cached dense-vlad vocabulary {cached} is damaged or unreadable; "
                                         r"fitting it again\. \(Why: .*its centres no longer match the checksum"):
        again = create_method("dense-vlad", vocabulary=str(foreign_images), cache_dir=tmp_path, **SMALL)
        assert again.fingerprint()["vocabulary"] == first  # the same seeded fit, the same centres
    assert torch.load(cached)["crc32"] is not None and not list(cached.parent.glob("*.tmp*"))


def test_file_vocabulary_is_checked_and_named(tmp_path, corridor_refs):
    good = tmp_path / "words.npy"
    np.save(good, np.random.default_rng(0).random((8, 128), dtype=np.float32))
    method = create_method("dense-vlad", vocabulary=str(good), **SMALL)
    assert method.describe([method.load(corridor_refs[0])]).shape == (1, 1024)
    info = method_provenance(method)["vocabulary"]
    assert info["source"] == "file" and info["fitted_on_evaluated_database"] is None
    assert info["fitted_on"].startswith("unknown (file sha256:")

    anyloc = tmp_path / "anyloc.pt"
    Vocabulary(torch.zeros(8, 1536), {"backbone": "dinov2_vitg14", "layer": 31, "facet": "value"}).save(anyloc)
    with pytest.raises(VPRBenchError, match=r"1536-dimensional centres \(made for dinov2_vitg14/31/value\), but "
                                            r"dense-vlad's RootSIFT descriptors are 128-dimensional"):
        create_method("dense-vlad", vocabulary=str(anyloc), **SMALL).fingerprint()
    with pytest.raises(VPRBenchError, match="has 8 clusters, the method asks for 16"):
        create_method("dense-vlad", vocabulary=str(good), clusters=16).fingerprint()
    with pytest.raises(VPRBenchError, match="vocabulary file .*missing.npy does not exist"):
        create_method("dense-vlad", vocabulary=str(tmp_path / "missing.npy"))


def test_unknown_vocabulary_lists_what_it_takes():
    with pytest.raises(VPRBenchError, match="option vocabulary takes map .* got '17plac'. Did you mean: 17places"):
        create_method("dense-vlad", vocabulary="17plac")


def test_dataset_vocabulary_fits_on_that_database_and_is_transductive_only_there(shared_data, tmp_path, corridor_refs):
    method = create_method("dense-vlad", vocabulary="corridor", cache_dir=tmp_path, data_dir=shared_data,
                           sample=800, **SMALL)
    method.use_dataset("17places")
    method.vocabulary_centres()
    info = method.provenance()["vocabulary"]
    assert info["datasets"] == {"corridor": 111} and info["fitted_on_evaluated_database"] is False
    assert "the database of corridor (protocol" in info["fitted_on"]
    method.use_dataset("corridor")
    assert method.provenance()["vocabulary"]["fitted_on_evaluated_database"] is True
    missing = create_method("dense-vlad", vocabulary="17places", cache_dir=tmp_path, data_dir=tmp_path, **SMALL)
    with pytest.raises(VPRBenchError, match="cannot fit the '17places' vocabulary: missing 17places"):
        missing.fingerprint()


def test_spec_names_a_benchmark_vocabulary_by_its_protocol_hash(shared_data):
    from vprbench.datasets import dataset_manifest, find_protocol
    from vprbench.spec import resolve_spec

    spec = resolve_spec("dense-vlad", "corridor", options={"vocabulary": "17places"})
    assert spec.files == {"vocabulary": f"protocol:{find_protocol(dataset_manifest('17places'), None).hash}"}
    assert spec.method_identity()["options"]["vocabulary"] == spec.files["vocabulary"]
    assert spec.row_key != resolve_spec("dense-vlad", "corridor").row_key


def test_folder_of_the_evaluated_images_is_marked_transductive_by_content(shared_data, tmp_path):
    from vprbench.datasets import load_dataset

    corridor = load_dataset("corridor", shared_data)
    folder = tmp_path / "copied"  # a copy elsewhere: found by content, not by path
    folder.mkdir()
    for path in corridor.database[:3]:
        (folder / path.name).write_bytes(path.read_bytes())
    method = create_method("dense-vlad", vocabulary=str(folder), cache_dir=tmp_path, sample=600, **SMALL)
    method.use_dataset("corridor")
    method.vocabulary_centres()
    assert method.provenance()["vocabulary"]["fitted_on_evaluated_database"] is False  # the method cannot tell
    found = method_provenance(method, corridor, tmp_path)
    assert found["vocabulary"]["fitted_on_evaluated_database"] is True
    assert found["vocabulary"]["evaluated_images_fitted_on"] == 3 and found["fitted_on_evaluated_database"] is True


def test_a_dense_vlad_vocabulary_given_to_anyloc_is_refused_naming_both(foreign_images, tmp_path):
    method = create_method("dense-vlad", vocabulary=str(foreign_images), cache_dir=tmp_path, **SMALL)
    method.vocabulary_centres()
    (fitted,) = (tmp_path / "vocabularies" / "dense-vlad").glob("*/vocabulary.pt")
    with pytest.raises(VPRBenchError, match=r"has 128-dimensional centres but the features are 384-dimensional: "
                                            r"it was fitted for other features .*: dense-vlad\)"):
        create_method("anyloc", backbone="dinov2_vits14", layer=9, vocabulary=str(fitted), clusters=8)


def test_evaluate_hands_the_data_folder_to_the_vocabulary_and_records_it(shared_data, tmp_path):
    from vprbench.evaluation.pipeline import evaluate
    from vprbench.spec import RunSettings, resolve_spec

    options = {"vocabulary": "corridor", "sample": 600, "clusters": 8, "bin_sizes": [6], "step": 8}
    spec = resolve_spec("dense-vlad", "corridor", options=options)
    record = evaluate(spec, RunSettings(cache_dir=tmp_path, data_dir=shared_data, workers=0))
    provenance = record["provenance"]
    assert provenance["learnt"] == ["vocabulary"] and provenance["fitted_on_evaluated_database"] is True
    assert provenance["vocabulary"]["datasets"] == {"corridor": 111}
    assert record["method_fingerprint"]["vocabulary"] == "sha256:" + provenance["vocabulary"]["centres_sha256"]
    assert record["descriptor_dim"] == 8 * 128 and 0 <= record["recall"]["1"] <= 100


def test_domain_vocabulary_names_every_missing_dataset(tmp_path):
    method = create_method("dense-vlad", vocabulary="indoor", cache_dir=tmp_path, data_dir=tmp_path, **SMALL)
    with pytest.raises(VPRBenchError) as info:
        method.fingerprint()
    assert all(name in str(info.value) for name in ("gardens-point", "17places", "baidu-mall"))
    assert str(info.value).startswith("dense-vlad: cannot fit the 'indoor' vocabulary: missing")


def test_kmeans_words_do_not_depend_on_the_thread_count():
    """Was: faiss's k-means ran on the machine's OpenMP count, and one sample gave another vocabulary at
    each of 1, 2, 3 and 8 threads (torchrun's one thread a vocabulary of its own)."""
    import faiss

    from vprbench.methods.dense_vlad import kmeans_words

    sample = np.random.default_rng(0).random((20_000, 128), dtype=np.float32)
    before = faiss.omp_get_max_threads()
    try:
        found = []
        for threads in (1, 3):
            faiss.omp_set_num_threads(threads)
            found.append(kmeans_words(sample, 64, seed=0))
            assert faiss.omp_get_max_threads() == threads  # the caller's count, restored
    finally:
        faiss.omp_set_num_threads(before)
    assert found[0].shape == (64, 128) and found[0].dtype == np.float32
    assert np.array_equal(found[0], found[1])
