"""The anyloc method: presets, options, fit/describe on real images, batch invariance."""
import numpy as np
import pytest
import torch

from vprbench import VPRBenchError, available_methods, create_method
from vprbench.features.backbones import backbone_spec, create_model
from release_formats import official_state_dict
from vprbench.methods.anyloc import AnyLoc
from vprbench.methods.builtin import anyloc_presets


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    torch.manual_seed(0)
    spec = backbone_spec("dinov2_vits14")
    path = tmp_path_factory.mktemp("w") / "dinov2_vits14_pretrain.pth"
    torch.save(official_state_dict(create_model(spec), spec), path)
    return path


@pytest.fixture
def corridor(shared_data):
    root = shared_data / "corridor"
    return sorted((root / "ref").glob("*.jpg"))[:6], sorted((root / "query").glob("*.jpg"))[:4]


def test_presets_are_the_papers():
    p = anyloc_presets()
    assert set(p) >= {"anyloc-vlad-dinov2", "anyloc-vlad-dinov2-pca", "anyloc-gem-dinov2", "anyloc-vlad-dino",
                      "anyloc-vlad-dino-pca", "dinov2-cls", "dino-cls"}
    assert p["anyloc-vlad-dinov2"]["options"] == dict(backbone="dinov2_vitg14", layer_for="dinov2_vitg14:31", facet="value",
                                                      aggregation="vlad", clusters=32, vocabulary="domain")  # the paper's, per dataset
    assert p["anyloc-vlad-dino"]["options"]["clusters"] == 128 and p["anyloc-vlad-dino"]["options"]["layer_for"] == "dino_vits8:9"
    assert p["anyloc-vlad-dinov2-pca"]["options"]["pca_dim"] == 512
    assert set(p) <= set(available_methods())


def test_end_to_end_vlad_on_corridor(weights, corridor):
    db, queries = corridor
    m = create_method("anyloc-vlad-dinov2", backbone="dinov2_vits14", weights=str(weights), layer=3, clusters=4)
    assert m.needs_fit
    with pytest.raises(VPRBenchError, match="fit"):
        m.describe(queries)
    m.fit(db)
    assert m.centres.shape == (4, 384)
    d = m.describe(queries)
    assert d.shape == (4, 4 * 384) and d.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1, atol=1e-5)
    # round trip of the vocabulary through the store's fit state
    again = create_method("anyloc-vlad-dinov2", backbone="dinov2_vits14", weights=str(weights), layer=3, clusters=4)
    again.load_fit_state(m.fit_state())
    np.testing.assert_array_equal(again.describe(queries), d)
    fp = m.fingerprint()
    assert fp["weights"].startswith("sha256:") and fp["layer"] == 3 and fp["clusters"] == 4 and fp["resize"] == "native"


def test_batch_size_does_not_change_descriptors(weights, shared_data, corridor):
    _, queries = corridor
    images = queries[:3] + [shared_data / "images" / "tokyo247-pair" / "tokyo_db.png"] + queries[3:]
    out = [create_method("anyloc-gem-dinov2", backbone="dinov2_vits14", weights=str(weights), layer=2,
                         resize=(120, 160), batch_size=b).describe(images) for b in (1, 3, 8)]
    assert out[0].shape == (5, 384)
    np.testing.assert_allclose(out[1], out[0], rtol=0, atol=1e-6)
    np.testing.assert_allclose(out[2], out[0], rtol=0, atol=1e-6)


def test_mixed_sizes_keep_input_order(weights, shared_data, corridor):
    _, queries = corridor
    tokyo = shared_data / "images" / "tokyo247-pair" / "tokyo_db.png"
    m = create_method("anyloc", backbone="dinov2_vits14", weights=str(weights), layer=1, aggregation="gap", batch_size=2)
    mixed = m.describe([queries[0], tokyo, queries[1]])
    alone = np.concatenate([m.describe([p]) for p in (queries[0], tokyo, queries[1])])
    np.testing.assert_allclose(mixed, alone, atol=1e-6)


def test_vocabulary_file_and_cls(weights, corridor, tmp_path):
    _, queries = corridor
    centres = torch.randn(3, 384)
    torch.save(centres, tmp_path / "c_centers.pt")
    m = create_method("anyloc", backbone="dinov2_vits14", weights=str(weights), layer=4,
                      vocabulary=str(tmp_path / "c_centers.pt"), clusters=3)
    assert not m.needs_fit and m.describe(queries[:1]).shape == (1, 3 * 384)
    assert m.fingerprint()["vocabulary"].startswith("sha256:")
    cls = create_method("dinov2-cls", backbone="dinov2_vits14", weights=str(weights)).describe(queries[:2])
    assert cls.shape == (2, 384)


def test_option_errors(weights):
    with pytest.raises(VPRBenchError, match="option aggregation takes one of vlad, .*; got 'netvlad'"):
        create_method("anyloc", aggregation="netvlad")
    with pytest.raises(VPRBenchError, match="needs a CUDA device"):
        create_method("anyloc-gem-dinov2", precision="fp16", device="cpu")
    with pytest.raises(VPRBenchError, match="does not take option"):
        create_method("anyloc", colour="red")
    with pytest.raises(VPRBenchError, match=r"option layer takes a whole number from 0 to 11 .*got 31"):
        create_method("anyloc-vlad-dinov2", backbone="dinov2_vits14", weights=str(weights), layer=31)  # before loading
    m = create_method("anyloc-vlad-dinov2-pca", backbone="dinov2_vits14", weights=str(weights), layer=0)
    with pytest.raises(VPRBenchError, match=r"PCA dimension 512 is larger than the number of database images \(3\)"):
        m.postprocess(np.eye(3, 8, dtype=np.float32), np.eye(2, 8, dtype=np.float32))


def test_preset_layer_moves_to_the_same_relative_depth_on_another_backbone(weights):
    assert create_method("anyloc-vlad-dinov2").layer == 31
    with pytest.warns(UserWarning, match="block 9 at the same relative depth"):
        assert create_method("anyloc-vlad-dinov2", backbone="dinov2_vits14").layer == 9  # 31/39 of 11 blocks
    with pytest.warns(UserWarning, match="block 18"):
        assert create_method("anyloc-gem-dinov2", backbone="dinov2_vitl14").layer == 18
    assert create_method("anyloc-vlad-dinov2", backbone="dinov2_vits14", layer=4).layer == 4  # the user's choice
    assert create_method("anyloc-vlad-dino", backbone="dino_vitb16").layer == 9  # same depth: unchanged


def test_a_layer_written_out_at_the_moved_depth_is_not_noted_as_the_presets(shared_data, tmp_path, capsys):
    """`--option layer=9` on ViT-S is the user's choice: same run as unset (same spec), but no note that
    the preset's ViT-G block 31 was moved there, neither from create_method nor from `evaluate`."""
    import warnings

    from vprbench.cli.main import main

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert create_method("anyloc-gem-dinov2", backbone="dinov2_vits14", layer=9, weights="random").layer == 9
    run = ["evaluate", "--method", "anyloc-gem-dinov2", "--option", "backbone=dinov2_vits14", "--option", "weights=random",
           "--option", "resize=28,28", "--dataset", "corridor", "--data-dir", str(shared_data), "--cache-dir", str(tmp_path)]

    def said(options):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            assert main(run + options) == 0
        return " ".join(str(w.message) for w in caught), " ".join(capsys.readouterr().out.split())

    assert "relative depth" not in said(["--option", "layer=9"])[0]
    notes, out = said([])  # unset: the note, and the same run (nothing computed again)
    assert "block 9 at the same relative depth" in notes and "descriptors computed now: 0" in out
    plan = tmp_path / "plan.toml"  # a sweep's cell is made from its options as written too
    plan.write_text('[[methods]]\nname = "anyloc-gem-dinov2"\noptions = { backbone = "dinov2_vits14", weights = '
                    '"random", resize = [28, 28], layer = 9 }\n\n[[datasets]]\nname = "corridor"\n')
    run[:] = ["run", str(plan), "--data-dir", str(shared_data), "--cache-dir", str(tmp_path / "sweep")]
    notes, out = said([])
    assert "relative depth" not in notes and " ran " in out, out


def test_a_layer_written_out_in_the_python_api_is_not_noted_as_the_presets(shared_data, tmp_path):
    """resolve_spec(options={"layer": 9}) on ViT-S then evaluate(spec): the method is made from the layer
    written, as on the command line (no note); unset, the note is said. The record states block 9 either way,
    and the layer written leaves the spec's identity and JSON as they are."""
    import warnings

    from vprbench.evaluation import evaluate
    from vprbench.spec import RunSettings, resolve_spec

    settings = RunSettings(data_dir=shared_data, cache_dir=tmp_path)
    options = {"backbone": "dinov2_vits14", "weights": "random", "resize": [28, 28]}

    def run(**layer):
        spec = resolve_spec("anyloc-gem-dinov2", "corridor", options={**options, **layer}, data_dir=shared_data,
                            cache_dir=tmp_path)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            record = evaluate(spec, settings)
        return spec, record, " ".join(str(w.message) for w in caught)

    written, record, notes = run(layer=9)
    assert "relative depth" not in notes and record["method_fingerprint"]["layer"] == 9
    unset, record, notes = run()
    assert "block 9 at the same relative depth" in notes and record["method_fingerprint"]["layer"] == 9
    assert (written.key, written.to_json()) == (unset.key, unset.to_json())


def test_dataset_resize_policy_feeds_fingerprint(weights):
    layer_note = "layer 31 is dinov2_vitg14's .* block 9 at the same relative depth"  # the ViT-G layer on ViT-S
    with pytest.warns(UserWarning, match=layer_note):
        m = AnyLoc(backbone="dinov2_vits14", weights=str(weights), aggregation="gem")
        m.use_dataset("pitts30k")
    assert m.fingerprint()["resize"] == [480, 640]
    with pytest.warns(UserWarning, match=layer_note):
        m = AnyLoc(backbone="dinov2_vits14", weights=str(weights), aggregation="gem", resize="224x224", dataset="pitts30k")
    assert m.fingerprint()["resize"] == [224, 224]


def test_resize_native_written_out_keeps_the_native_size(weights, corridor):
    """`resize=native` is the image's own size even where the policy resizes (Pitts-30k: 480x640),
    and a run of its own: not the unset option's."""
    from vprbench.spec import resolve_spec
    from vprbench.stages.patches import PatchMNNOptions

    (image, *_), _ = corridor  # 120 x 160
    shapes = {}
    for resize in (None, "native", "NATIVE", "none"):  # "none": how the option's one form writes native too
        m = AnyLoc(backbone="dinov2_vits14", weights=str(weights), layer=3, aggregation="gem", resize=resize)
        m.use_dataset("pitts30k")
        shapes[resize] = (tuple(m.load(image).shape), m.fingerprint()["resize"])
    assert shapes[None] == ((3, 476, 630), [480, 640])
    assert shapes["native"] == shapes["NATIVE"] == shapes["none"] == ((3, 112, 154), "native")  # cropped to whole 14-pixel patches
    unset, native = (resolve_spec("anyloc-gem-dinov2", "pitts30k", options={"weights": "random", "resize": r})
                     for r in (None, "native"))
    assert unset.key != native.key and native.options["resize"] == "native"
    assert PatchMNNOptions(resize="native").resize == "native" and PatchMNNOptions().resize is None


def test_released_centres_and_domain_vocabulary(shared_data, tmp_path, monkeypatch):
    released = shared_data / "vocabularies" / "anyloc-dinov2_vitg14-l31-value-c32" / "indoor" / "c_centers.pt"
    m = create_method("anyloc-vlad-dinov2", vocabulary=str(released))  # no weights needed to resolve
    assert not m.needs_fit and m.centres.shape == (32, 1536)
    fp = m.fingerprint()
    assert fp["vocabulary"].startswith("sha256:") and fp["weights"].endswith("dinov2_vitg14_pretrain.pth")
    domain = create_method("anyloc-vlad-dinov2", vocabulary="domain")
    assert domain.centres is None and domain.needs_fit  # settled by use_dataset
    import socket

    def offline(*args, **kwargs):
        raise OSError("network disabled in tests")

    monkeypatch.setattr(socket.socket, "connect", offline)
    with pytest.raises(VPRBenchError, match="Cannot download the authors' 'indoor' centres.*put the file at"):
        domain.use_dataset("baidu-mall")
    with pytest.raises(VPRBenchError, match="has 32 clusters, the method asks for 8"):
        create_method("anyloc-vlad-dinov2", vocabulary=str(released), clusters=8)


def test_patch_feature_stream_in_input_order(weights, corridor, shared_data):
    _, queries = corridor
    tokyo = shared_data / "images" / "tokyo247-pair" / "tokyo_db.png"
    m = create_method("anyloc-vlad-dinov2", backbone="dinov2_vits14", weights=str(weights), layer=1, batch_size=3)
    feats = list(m.iter_patch_features([queries[0], tokyo, queries[1]], resize=(28, 42)))
    assert [tuple(f.shape) for f in feats] == [(6, 384)] * 3
    np.testing.assert_allclose(torch.stack(feats).norm(dim=-1).numpy(), 1, atol=1e-5)
    native = list(m.iter_patch_features([queries[0], tokyo]))
    assert [tuple(f.shape) for f in native] == [(88, 384), (45 * 34, 384)]


def test_dino_v1_path_end_to_end(corridor, tmp_path):
    torch.manual_seed(3)
    spec = backbone_spec("dino_vits8")
    torch.save(official_state_dict(create_model(spec), spec), tmp_path / spec.file_name)
    torch.save(torch.randn(2, 384), tmp_path / "c.pt")
    _, queries = corridor
    # weights given as the folder holding the official file
    m = create_method("anyloc-vlad-dino", weights=str(tmp_path), layer=1, clusters=2, vocabulary=str(tmp_path / "c.pt"))
    assert m.stride == 4 and m.fingerprint()["preprocess"] == "dino-official"
    feats = next(iter(m.iter_patch_features(queries[:1])))
    assert feats.shape == (55 * 73, 384)  # 224x298 at stride 4: 1 + (224-8)//4 by 1 + (298-8)//4
    assert m.describe(queries[:1]).shape == (1, 2 * 384)


def test_the_block_or_stride_an_unset_option_stands_for_written_out_is_the_same_run():
    """`--layer 31` on anyloc-vlad-dinov2 (ViT-G's block 31 is its preset), block 9 on ViT-S/14 (the same
    relative depth) and DINO's stride 4 are what the unset options run: one spec key and label each."""
    from vprbench.spec import resolve_spec

    def spec(method, **options):
        return resolve_spec(method, "corridor", options=options)

    same = [(spec("anyloc-vlad-dinov2"), spec("anyloc-vlad-dinov2", layer=31)),
            (spec("anyloc-vlad-dinov2", backbone="dinov2_vits14"), spec("anyloc-vlad-dinov2", backbone="dinov2_vits14", layer=9, stride=14)),
            (spec("anyloc-vlad-dino"), spec("anyloc-vlad-dino", layer=9, stride=4))]
    for unset, written in same:
        assert (written.key, written.label()) == (unset.key, unset.label())
    assert spec("anyloc-vlad-dinov2", layer=30).label() == "anyloc-vlad-dinov2 [layer=30]"
    assert spec("anyloc-vlad-dino", stride=8).key != spec("anyloc-vlad-dino").key


def test_fp16_runs_get_the_same_implied_layer_and_named_vocabulary_identity(tmp_path):
    """precision=fp16 needs CUDA, which a probe on this host lacks: the layer written out is still the
    same run, and a vocabulary named by source is still in the key (a refit is another run)."""
    import torch

    from vprbench.aggregation.vocabulary import Vocabulary
    from vprbench.methods.anyloc_vocabulary import save_to_cache
    from vprbench.spec import resolve_spec

    half = {"precision": "fp16"}
    assert resolve_spec("anyloc-vlad-dinov2", "corridor", options={**half, "layer": 31}).key == \
        resolve_spec("anyloc-vlad-dinov2", "corridor", options=half).key
    centres = torch.nn.functional.normalize(torch.randn(4, 384, generator=torch.Generator().manual_seed(0)), dim=1)
    save_to_cache(Vocabulary(centres, {}), "dinov2_vits14@random", 1, "value", "indoor", tmp_path)
    options = {"backbone": "dinov2_vits14", "weights": "random", "layer": 1, "clusters": 4, "vocabulary": "indoor"}
    found = [resolve_spec("anyloc", "corridor", options={**options, **extra}, cache_dir=tmp_path).found
             for extra in ({}, half)]
    assert found[0]["vocabulary"].startswith("sha256:") and found[1] == found[0]


def test_an_on_demand_fit_of_more_clusters_than_patches_is_refused_before_any_image_is_read(tmp_path):
    """vocabulary=map fits on the database in the run: too many clusters were found out once every image was
    described. At 28 x 28 each image gives 2 x 2 patches of 14 (these images do not exist: none is read)."""
    method = AnyLoc(backbone="dinov2_vits14", weights="random", layer=0, clusters=13, resize=[28, 28])
    assert method.patches_per_image() == 4 and method.patches_per_image((56, 70)) == 20
    with pytest.raises(VPRBenchError, match=r"Cannot fit 13 clusters on 12 features \(3 images x 4 patches each"):
        method.fit([tmp_path / f"{i}.jpg" for i in range(3)])
    assert AnyLoc(backbone="dinov2_vits14", weights="random", layer=0).patches_per_image() is None  # native size


def test_a_fit_in_the_run_records_its_sampling(weights, corridor):
    """The paper's k-means sees every patch of the database; a run's fit keeps a seeded sample of at most the budget:
    its record says so (exact, budget, features seen and used), also when the fit is read back from its store."""
    from vprbench.aggregation.kmeans import DEFAULT_BUDGET

    db, _ = corridor
    m = create_method("anyloc-vlad-dinov2", backbone="dinov2_vits14", weights=str(weights), layer=3, clusters=4)
    m.fit(db)
    sampling = m.provenance()["vocabulary"]["sampling"]
    assert sampling["exact"] is False and sampling["budget"] == DEFAULT_BUDGET
    assert sampling["features_seen"] == sampling["features_used"] > 0  # corridor's 6 images fit in the budget
    again = create_method("anyloc-vlad-dinov2", backbone="dinov2_vits14", weights=str(weights), layer=3, clusters=4)
    again.load_fit_state(m.fit_state())
    assert again.provenance()["vocabulary"]["sampling"] == sampling


def test_a_vocabulary_file_records_its_sampling(tmp_path):
    """A `vocabulary fit` file's sampling (its metadata) reaches the record of a run reading it."""
    from vprbench.aggregation.vocabulary import Vocabulary, load_vocabulary
    from vprbench.methods.anyloc_provenance import file_provenance

    meta = {"exact": False, "budget": 100, "features_seen": 500, "features_used": 100}
    Vocabulary(torch.randn(4, 8), meta).save(tmp_path / "v.pt")
    assert file_provenance(load_vocabulary(tmp_path / "v.pt"))["sampling"] == meta
