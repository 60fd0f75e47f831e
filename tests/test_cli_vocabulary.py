import argparse
import os
import re

import numpy as np
import pytest
import torch

from own_folders import corridor_folder
from vprbench import Method
from vprbench.aggregation import Vocabulary
from vprbench.methods.anyloc_lookup import resolve_vocabulary
from vprbench.cli import vocabulary as cli
from vprbench.errors import VPRBenchError


def run(args):
    return args.run(args)


def parse(*argv):
    parser = argparse.ArgumentParser(prog="vprbench")
    cli.add_parsers(parser.add_subparsers(dest="command"))
    return parser.parse_args(argv)


def test_import_then_resolve_by_name(tmp_path, capsys):
    Vocabulary(torch.randn(3, 384)).save(tmp_path / "mine.pt")  # dinov2_vits14's width: other centres are refused
    assert run(parse("vocabulary", "import", str(tmp_path / "mine.pt"), "--source", "urban",
                         "--backbone", "dinov2_vits14", "--layer", "9", "--facet", "key")) == 0
    found = resolve_vocabulary("urban", "dinov2_vits14", 9, "key", 3)
    assert found.centres.shape == (3, 384) and found.meta["source"] == "urban"
    out = capsys.readouterr().out
    assert "Imported 3 x 384 centres as 'urban'" in out and "replacing" not in out
    # was: a second import under the name replaced the first without a word
    Vocabulary(torch.randn(3, 384)).save(tmp_path / "other.pt")
    assert run(parse("vocabulary", "import", str(tmp_path / "other.pt"), "--source", "urban",
                     "--backbone", "dinov2_vits14", "--layer", "9", "--facet", "key")) == 0
    assert "(replacing the centres cached as 'urban' before; runs naming it are run again)" in capsys.readouterr().out
    torch.testing.assert_close(resolve_vocabulary("urban", "dinov2_vits14", 9, "key", 3).centres,
                               Vocabulary(torch.load(tmp_path / "other.pt")["centres"]).centres)


def test_import_for_ones_own_checkpoint_takes_its_digest(tmp_path, capsys):
    """Centres for a user's checkpoint go under BACKBONE@<16 hex of its sha256>; another suffix is refused."""
    Vocabulary(torch.randn(3, 384)).save(tmp_path / "mine.pt")
    digest = "0123456789abcdef"
    assert run(parse("vocabulary", "import", str(tmp_path / "mine.pt"), "--source", "urban",
                     "--backbone", f"dinov2_vits14@{digest}", "--layer", "9", "--facet", "key")) == 0
    assert resolve_vocabulary("urban", f"dinov2_vits14@{digest}", 9, "key", 3).meta["backbone"] == f"dinov2_vits14@{digest}"
    for suffix in ("mine", "0123456789ABCDEF", digest + "0"):
        with pytest.raises(VPRBenchError, match="after '@' give 'random' or the first 16 hex digits"):
            run(parse("vocabulary", "import", str(tmp_path / "mine.pt"), "--source", "rural",
                      "--backbone", f"dinov2_vits14@{suffix}", "--layer", "9", "--facet", "key"))


def test_show_and_domains(tmp_path, capsys):
    Vocabulary(torch.zeros(2, 4), {"backbone": "b"}).save(tmp_path / "v.pt")
    run(parse("vocabulary", "show", str(tmp_path / "v.pt")))
    run(parse("vocabulary", "domains"))
    out = capsys.readouterr().out
    assert "2 clusters x 4 dims" in out and "backbone: b" in out
    assert "urban: oxford:1, st-lucia:1, pitts30k:4" in out and "320x320" in out


def test_fit_needs_domain_or_dataset_and_key_value_options():
    with pytest.raises(SystemExit):
        parse("vocabulary", "fit")
    with pytest.raises(SystemExit):
        parse("vocabulary", "fit", "--domain", "indoor", "--dataset", "corridor", "--method", "m")
    args = parse("vocabulary", "fit", "--domain", "indoor", "--method", "m", "-o", "layer")
    with pytest.raises(VPRBenchError, match="KEY=VALUE"):
        run(args)


class FakeMethod(Method):
    """Stands in for AnyLoc: 4x4 grey-level patches of the real image as 'patch features'."""

    name, backbone, layer, facet = "fake", "fake", 0, "token"

    def __init__(self, clusters=None, **options):
        self.clusters, self.seen, self.resizes, self.dataset = int(clusters or 32), [], set(), None

    def use_dataset(self, name):
        self.dataset = name

    def describe(self, images):
        raise AssertionError("a fit reads patch features only")

    def iter_patch_features(self, paths, resize=None):
        from vprbench.images import load_rgb

        self.resizes.add(resize)
        for path in paths:
            self.seen.append(path)
            grey = torch.tensor(load_rgb(path)).float().mean(-1)[:120, :160]
            yield grey.reshape(30, 4, 40, 4).permute(0, 2, 1, 3).reshape(-1, 16) + 1.0


def test_fit_map_vocabulary_on_real_dataset(shared_data, monkeypatch, capsys, tmp_path):
    import vprbench.methods as methods

    made = []
    monkeypatch.setattr(methods, "create_method", lambda name, **kw: made.append(FakeMethod(**kw)) or made[-1])
    args = parse("vocabulary", "fit", "--dataset", "corridor", "--method", "fake", "--clusters", "8",
                 "--budget", "5000", "--output", str(tmp_path / "out.pt"), "--data-dir", str(shared_data))
    assert run(args) == 0
    assert len(made[0].seen) == 111 and made[0].resizes == {None} and made[0].dataset == "corridor"
    found = resolve_vocabulary("map-corridor", "fake", 0, "token", 8)
    assert found.centres.shape == (8, 16)
    assert found.meta["features_seen"] == 111 * 1200 and found.meta["features_used"] == 5000
    assert found.meta["datasets"] == {"corridor": 111}
    assert "5000 of 133200 features" in capsys.readouterr().out and (tmp_path / "out.pt").is_file()


def test_fit_with_the_anyloc_method_then_use_by_name(shared_data, tmp_path, capsys):
    """The real AnyLoc features (random-initialised ViT-S/14, block 0) through the CLI."""
    from vprbench import create_method
    from vprbench.features.backbones import backbone_spec, create_model
    from release_formats import official_state_dict

    torch.manual_seed(0)
    spec = backbone_spec("dinov2_vits14")
    weights = tmp_path / "dinov2_vits14_pretrain.pth"
    torch.save(official_state_dict(create_model(spec), spec), weights)
    options = ["--backbone", "dinov2_vits14", "--weights", str(weights), "--layer", "0", "--clusters", "4"]
    args = parse("vocabulary", "fit", "--dataset", "corridor", "--method", "anyloc-vlad-dinov2", *options,
                 "--budget", "3000", "--data-dir", str(shared_data))
    assert run(args) == 0
    # 111 images of 160x120 -> 154x112 after the crop -> 11 x 8 patches
    assert "3000 of 9768 features" in capsys.readouterr().out
    method = create_method("anyloc-vlad-dinov2", backbone="dinov2_vits14", weights=str(weights), layer=0,
                           clusters=4, vocabulary="map-corridor")
    images = sorted((shared_data / "corridor" / "query").glob("*.jpg"))[:2]
    out = method.describe(images)
    assert out.shape == (2, 4 * 384) and np.allclose(np.linalg.norm(out, axis=1), 1, atol=1e-5)


def test_a_missing_domain_vocabulary_says_the_fit_command_of_the_run(shared_data, tmp_path, capsys):
    """It said "Fit it with `vprbench vocabulary fit --method METHOD --domain indoor ...`": neither the method nor
    the options keying the vocabulary (random weights) nor the run's folders. Now the dry run's command, to paste."""
    import shlex

    from vprbench.cli.main import build_parser, main
    from vprbench.cli.options import method_options
    from vprbench.methods import create_method

    cache = tmp_path / "my cache"
    code = main(["evaluate", "--method", "anyloc-vlad-dinov2", "--weights", "random", "--vocabulary", "indoor",
                 "--dataset", "corridor", "--data-dir", str(shared_data), "--cache-dir", str(cache)])
    err = capsys.readouterr().err
    assert code == 1 and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    command = shlex.split(err.split("Fit it with `", 1)[1].split("`", 1)[0])
    assert command[:7] == ["vprbench", "vocabulary", "fit", "--domain", "indoor", "--method", "anyloc-vlad-dinov2"]
    args = build_parser().parse_args(command[1:])
    assert (str(args.data_dir), str(args.cache_dir)) == (str(shared_data), str(cache))
    # run as said, the fit caches its centres under the key this run looks in
    keyed = ("vocabulary_backbone", "layer", "facet", "clusters", "stride")
    fitted, run = create_method(args.method, **method_options(args)), create_method("anyloc-vlad-dinov2", weights="random")
    assert [getattr(fitted, a) for a in keyed] == [getattr(run, a) for a in keyed] == ["dinov2_vitg14@random", 31,
                                                                                        "value", 32, 14]


def test_a_named_vocabulary_that_is_no_domain_is_not_told_to_fit_one(tmp_path):
    """'urbn' cannot be fitted with `--domain urbn` (no such domain): the error names the near domain and import."""
    with pytest.raises(VPRBenchError) as caught:
        resolve_vocabulary("urbn", "dinov2_vits14", 9, "value", 4, tmp_path)
    said = str(caught.value)
    assert "Did you mean: urban?" in said and "vocabulary import FILE --source urbn" in said
    assert "--domain urbn" not in said and "\n" not in said
    with pytest.raises(VPRBenchError, match=r"Fit it with `vprbench vocabulary fit --domain urban --method anyloc --backbone "
                                                  r"dinov2_vits14 --layer 9 --facet value --clusters 4`"):
        resolve_vocabulary("urban", "dinov2_vits14", 9, "value", 4, tmp_path)


def test_fit_logs_its_progress_and_quiet_logs_none(shared_data, monkeypatch, capsys):
    """Describing the images is most of a fit: a batch job's log counts them, then the k-means says it is alive."""
    import vprbench.methods as methods
    from vprbench import progress

    monkeypatch.setattr(progress, "LOG_INTERVAL_S", 0.0)  # a line at every image
    monkeypatch.setattr(methods, "create_method", lambda name, **kw: FakeMethod(**kw))
    argv = ["vocabulary", "fit", "--dataset", "corridor", "--method", "fake", "--clusters", "2", "--budget", "500",
            "--data-dir", str(shared_data)]
    assert run(parse(*argv)) == 0
    err = capsys.readouterr().err.splitlines()
    counted = [line for line in err if line.startswith("progress: vocabulary map-corridor images ")]
    assert counted[0].startswith("progress: vocabulary map-corridor images 1/111 (1 %)"), err
    assert counted[-1].startswith("progress: vocabulary map-corridor images done 111/111 (100 %)"), err
    assert len(counted) == 111  # one line per image, the last one saying done
    others = {re.sub(r", \d+ s elapsed| done in \d+ s", "", line) for line in err if line not in counted}
    assert others <= {"progress: vocabulary map-corridor k-means (2 clusters, 500 features)"}, others
    assert run(parse(*argv, "--quiet")) == 0
    assert capsys.readouterr().err == ""


def test_a_map_fit_describes_the_database_at_the_size_its_runs_do(tmp_path, capsys):
    """`vocabulary fit --dataset 17places` fitted on native-size images while every AnyLoc run on 17 Places
    resizes to 480 x 640 (its in-run map fit too): centres of other features than the runs'."""
    from PIL import Image

    folder, count = tmp_path / "data" / "17places", 406  # the manifest's counts: a copy of another size is refused
    image = tmp_path / "one.jpg"
    Image.fromarray(np.full((60, 80, 3), 90, np.uint8)).save(image)
    for split in ("ref", "query"):
        (folder / split).mkdir(parents=True)
        for i in range(count):
            os.link(image, folder / split / f"{i}.jpg")
    rows = np.empty((count, 2), dtype=object)
    for i in range(count):
        rows[i, 0], rows[i, 1] = i, [i]
    np.save(folder / "ground_truth_new.npy", rows, allow_pickle=True)
    args = parse("vocabulary", "fit", "--dataset", "17places", "--method", "anyloc", "--backbone", "dinov2_vits14",
                 "--weights", "random", "--layer", "0", "--clusters", "4", "--budget", "2000",
                 "--data-dir", str(tmp_path / "data"), "--cache-dir", str(tmp_path / "cache"), "--quiet")
    assert run(args) == 0
    # 480 x 640 -> 476 x 630 after the crop to the patch -> 34 x 45 patches per image (native: 4 x 5)
    assert f"of {count * 34 * 45} features" in capsys.readouterr().out
    found = resolve_vocabulary("map-17places", "dinov2_vits14@random", 0, "value", 4, tmp_path / "cache")
    assert found.meta["resize"] == [480, 640]


def test_a_map_fit_looks_for_no_domain_vocabulary(tmp_path, capsys):
    """A method whose vocabulary option is 'domain' (AnyLoc-VLAD-DINOv2's preset) took the dataset's domain
    centres when the map fit applied the dataset's settings: a warning that the run falls back to the map
    (and, for the authors' setting, their centres fetched), for a fit that makes its own."""
    args = parse("vocabulary", "fit", "--dataset", "pitts30k", "--method", "anyloc", "--backbone", "dinov2_vits14",
                 "--weights", "random", "--layer", "0", "-o", "vocabulary=domain", "--data-dir", str(tmp_path / "none"),
                 "--cache-dir", str(tmp_path / "cache"), "--quiet")
    import warnings

    missing = "pitts30k: Dataset 'pitts30k' is not in"
    with warnings.catch_warnings(record=True) as caught, pytest.raises(VPRBenchError, match=missing):
        warnings.simplefilter("always")
        run(args)
    assert not [str(w.message) for w in caught if "vocabulary for" in str(w.message)]


@pytest.mark.parametrize("given", ["./campus-folder", "campus-folder"])
def test_a_map_fit_on_a_folder_is_named_by_its_dataset_not_the_path(given, shared_data, monkeypatch, capsys, tmp_path):
    """`--dataset ./mydata` was saved as 'map-./mydata' (folder 'map-._mydata'), a name no run could give back:
    --vocabulary map-./mydata is read as a file path."""
    import vprbench.methods as methods

    own = corridor_folder(shared_data, tmp_path / "campus-folder")
    (own / "dataset.toml").write_text('name = "campus"\n')
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(methods, "create_method", lambda name, **kw: FakeMethod(**kw))
    assert run(parse("vocabulary", "fit", "--dataset", given, "--method", "fake", "--clusters", "4")) == 0
    name = re.search(r"Vocabulary (map-campus-[0-9a-f]{12}): 4 x 16", capsys.readouterr().out)[1]  # and its content
    found = resolve_vocabulary(name, "fake", 0, "token", 4)
    assert found.meta["source"] == name and found.meta["datasets"] == {"campus": 3}


def test_two_folders_of_one_name_keep_their_own_map_vocabularies(shared_data, monkeypatch, capsys, tmp_path):
    """/x/a/place and /x/b/place (other images) were both cached as 'map-place': fitted on one, a run on the other
    named map-place took centres fitted on another map, and a fit on the other replaced them."""
    import vprbench.methods as methods

    a = corridor_folder(shared_data, tmp_path / "a" / "place", database=3)
    b = corridor_folder(shared_data, tmp_path / "b" / "place", database=4)
    cache = tmp_path / "cache"
    monkeypatch.setattr(methods, "create_method", lambda name, **kw: FakeMethod(**kw))
    names = []
    for folder in (a, b):
        assert run(parse("vocabulary", "fit", "--dataset", str(folder), "--method", "fake", "--clusters", "4",
                         "--cache-dir", str(cache), "--quiet")) == 0
        names.append(re.search(r"Vocabulary (map-place-[0-9a-f]{12}):", capsys.readouterr().out)[1])
    assert names[0] != names[1]
    from vprbench.paths import cache_root

    # the images' hashes memoised in the cache given (was: the user's default cache, whatever --cache-dir said)
    assert (cache / "image-hashes.sqlite").is_file() and not (cache_root() / "image-hashes.sqlite").exists()
    for name, folder, count in zip(names, (a, b), (3, 4)):
        found = resolve_vocabulary(name, "fake", 0, "token", 4, cache)
        assert found.meta["folder"] == str(folder.resolve()) and found.meta["datasets"] == {"place": count}
    with pytest.raises(VPRBenchError) as caught:  # which folder's? none is taken for another
        resolve_vocabulary("map-place", "fake", 0, "token", 4, cache)
    said = str(caught.value)
    assert all(str(part) in said for part in (*names, a.resolve(), b.resolve())) and "\n" not in said, said


def test_an_own_folders_map_vocabulary_is_fitted_on_the_evaluated_database_by_its_images_not_its_name(shared_data,
                                                                                                       tmp_path, capsys):
    """map-place-<a's content> on /x/b/place (other images) was marked "fitted on the evaluated database": the
    names matched. On a itself it is; the record names the folder and the vocabulary it was fitted as."""
    from vprbench import create_method
    from vprbench.datasets import load_dataset
    from vprbench.evaluation.provenance import method_provenance
    from vprbench.methods.anyloc_fit import fit_map_vocabulary
    from vprbench.methods.anyloc_vocabulary import save_to_cache

    a = corridor_folder(shared_data, tmp_path / "a" / "place", database=3)
    b = corridor_folder(shared_data, tmp_path / "b" / "place", database=3, first=3)  # one name, other images
    cache, setting = tmp_path / "cache", ("dino_vits8@random", 1, "key")  # its features never computed
    fitted = fit_map_vocabulary(str(a), lambda paths: (torch.randn(40, 384) for _ in paths), 4, cache_dir=cache)
    name = fitted.meta["source"]
    path = save_to_cache(fitted, *setting, name, cache, stride=4)
    method = create_method("anyloc", backbone="dino_vits8", weights="random", layer=1, facet="key", clusters=4,
                           vocabulary=name, cache_dir=cache)
    for folder, flagged in ((b, False), (a, True)):
        dataset = load_dataset(str(folder), cache_dir=cache)
        method.use_dataset(dataset.name)
        found = method_provenance(method, dataset, cache)
        assert found["fitted_on_evaluated_database"] is flagged, (folder, found)
        assert found["vocabulary"]["fitted_on"] == f"the database of the folder {a.resolve()} ({name})", found
    assert found["vocabulary"]["evaluated_images_fitted_on"] == 3
    run(parse("vocabulary", "show", str(path)))
    assert "  image_digests: 3 sha256 (of the images fitted on)\n" in capsys.readouterr().out  # not a list of hex
    del fitted.meta["image_digests"]  # a fit that did not record its images: which they were is not known
    save_to_cache(fitted, *setting, name, cache, stride=4)
    unknown = create_method("anyloc", backbone="dino_vits8", weights="random", layer=1, facet="key", clusters=4,
                            vocabulary=name, cache_dir=cache)
    unknown.use_dataset("place")
    assert method_provenance(unknown, dataset, cache)["fitted_on_evaluated_database"] is None


def test_a_folders_image_digests_at_pitts250k_size_are_kept_as_bytes(tmp_path):
    """The largest folder a map vocabulary serves: Pitts-250k's 254,064 database images. Kept as one hex
    string each, its file held 19 MB of pickled strings (0.9 s to load on every run using it)."""
    import hashlib

    from vprbench.aggregation.vocabulary import load_vocabulary
    from vprbench.methods.anyloc_fit import packed_digests, recorded_image_digests

    digests = [hashlib.sha256(i.to_bytes(4, "little")).hexdigest() for i in range(254_064)]
    saved = Vocabulary(torch.zeros(32, 1536), {"image_digests": packed_digests(digests[::-1] + digests[:5])})
    path = saved.save(tmp_path / "vocabulary.pt")
    assert path.stat().st_size < 1.6 * 32 * 254_064 + 32 * 1536 * 4 + 2**20  # torch pickles bytes as latin-1 text
    assert recorded_image_digests(load_vocabulary(path)) == set(digests)
    assert recorded_image_digests(Vocabulary(torch.zeros(2, 4), {"image_digests": b"\0" * 33})) == set()  # torn


def test_a_map_vocabulary_of_a_folder_fitted_before_names_carried_its_content_is_refused(tmp_path):
    """Cached as 'map-place' by an earlier vprbench: any folder named place would be served it."""
    from vprbench.methods.anyloc_vocabulary import save_to_cache

    old = Vocabulary(torch.randn(4, 16), {"source": "map-place", "datasets": {"place": 3}, "features_seen": 48})
    save_to_cache(old, "fake", 0, "token", "map-place", tmp_path)
    refit = Vocabulary(torch.randn(4, 16), {"source": "map-place-0123456789ab", "datasets": {"place": 3},
                                            "folder": "/data/place"})
    save_to_cache(refit, "fake", 0, "token", "map-place-0123456789ab", tmp_path)  # fitted again since
    with pytest.raises(VPRBenchError) as caught:  # was: "fit it again" alone, the refit's name never given
        resolve_vocabulary("map-place", "fake", 0, "token", 4, tmp_path)
    said = str(caught.value)
    assert "fitted on a folder of your own named 'place' before" in said and "\n" not in said, said
    assert "cached are map-place-0123456789ab (fitted on /data/place)" in said, said
    assert said.endswith("Fit it again (`vprbench vocabulary fit --method METHOD --dataset YOUR-FOLDER ...` with this "
                         "run's options) and give the name it prints, map-place-<12 hex digits>."), said
    imported = Vocabulary(torch.randn(4, 16), {"datasets": {"place": 3}, "imported_from": "/x/c_centers.pt"})
    save_to_cache(imported, "fake", 0, "token", "map-place", tmp_path)  # named so by its user: served
    assert resolve_vocabulary("map-place", "fake", 0, "token", 4, tmp_path).meta["imported_from"] == "/x/c_centers.pt"


@pytest.mark.parametrize("source", ["map-campus-0123456789ab", "map-my.data+1", "map-pitts30k", "mine"])
def test_import_takes_a_folder_of_ones_owns_map_name(source, tmp_path, capsys):
    Vocabulary(torch.randn(3, 384)).save(tmp_path / "mine.pt")
    assert run(parse("vocabulary", "import", str(tmp_path / "mine.pt"), "--source", source, "--backbone",
                     "dinov2_vits14", "--layer", "9", "--cache-dir", str(tmp_path / "cache"))) == 0
    assert resolve_vocabulary(source, "dinov2_vits14", 9, "value", 3, tmp_path / "cache").clusters == 3


class CountedFake(FakeMethod):
    """FakeMethod whose features per image are known before any image is read, as AnyLoc's at a set resize."""

    def patches_per_image(self, resize=None):
        return 30 * 40


@pytest.mark.parametrize("more, said", [
    (["--clusters", "200000", "--budget", "300000"], "Cannot fit 200000 clusters on 133,200 features (111 images x "
                                                     "1,200 patches each at this input size): give at most 133200 clusters, or fit on more images"),
    (["--clusters", "600", "--budget", "500"], "Cannot fit 600 clusters on a sample of at most 500 features"),
])
def test_more_clusters_than_the_fit_has_features_are_refused_before_any_image_is_described(
        more, said, shared_data, monkeypatch, tmp_path):
    """--clusters beyond the features a fit can have was refused by the k-means, after every image was described."""
    import vprbench.methods as methods

    made = []
    monkeypatch.setattr(methods, "create_method", lambda name, **kw: made.append(CountedFake(**kw)) or made[-1])
    args = parse("vocabulary", "fit", "--dataset", "corridor", "--method", "fake", *more, "--data-dir",
                 str(shared_data), "--cache-dir", str(tmp_path / "cache"), "--quiet")
    with pytest.raises(VPRBenchError) as caught:
        run(args)
    assert said in str(caught.value) and "\n" not in str(caught.value)
    assert made[0].seen == [] and not list((tmp_path / "cache").rglob("*.pt"))
