"""The superpoint-lightglue re-ranker: found through its entry point, release-format files (random tensors
with the released names and shapes) loaded through its real loading path, Corridor candidates re-ranked
by match counts, features computed once, random weights recorded and kept off the board, bad files and
options refused before anything is stored."""
import copy
import hashlib
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from vprbench.cli.main import main
from vprbench.datasets import load_dataset
from vprbench.errors import VPRBenchError
from vprbench.evaluation import read_results
from vprbench.images import load_rgb
from vprbench.leaderboard import build_board
from vprbench.leaderboard.cells import RANDOM
from vprbench.spec import resolve_spec
from vprbench.stages import Candidates, StageContext, create_stage

from oracles import PLACES, Images, assert_oracle, variants, worst_first

NAME = "superpoint-lightglue"
#: small and fast: SuperPoint on 64x48 images, few keypoints; random LightGlue weights are never confident,
#: so a tiny match threshold lets them give matches to count
SMALL = {"resize": 64, "max_keypoints": 48, "filter_threshold": 1e-7}
#: smaller still, for a run over all of Corridor: 32x24 images, no early stopping or pruning to check
TINY = {**SMALL, "resize": 32, "depth_confidence": -1, "width_confidence": -1}


@pytest.fixture(scope="module")
def release(tmp_path_factory, official_checkpoint):
    """A folder of the two release files in the official format: Magic Leap's 2018 file is a legacy
    (pre-zip) torch file, LightGlue's a zip one; random tensors with the released names and shapes."""
    folder = tmp_path_factory.mktemp("release")
    superpoint = official_checkpoint("superpoint", "superpoint_v1", seed=1)
    lightglue = official_checkpoint("lightglue", "superpoint_lightglue", seed=2)
    torch.save(superpoint, folder / "superpoint_v1.pth", _use_new_zipfile_serialization=False)
    torch.save(lightglue, folder / "superpoint_lightglue.pth")
    return folder, superpoint, lightglue


@pytest.fixture(scope="module")
def corridor(shared_data, tmp_path_factory):
    return load_dataset("corridor", shared_data, cache_dir=tmp_path_factory.mktemp("corridor-cache"))


def run(capsys, *args):
    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return code, out, err


def test_listed_with_where_it_comes_from(capsys):
    code, out, _ = run(capsys, "stages", "list", "--json")
    listed = {s["name"]: s for s in json.loads(out)}
    assert code == 0 and listed[NAME]["source"] == "vprbench_baselines" and listed[NAME]["track"] == "re-ranked"
    assert listed[NAME]["options"]["weights"] is None and listed[NAME]["options"]["resize"] == 1024


def test_release_files_load_exactly(release, tmp_path):
    from vprbench_baselines.lightglue import SuperPointLightGlueOptions, load_models

    folder, superpoint, lightglue = release
    sp, lg = load_models(SuperPointLightGlueOptions(weights=str(folder)))
    assert all(torch.equal(sp.state_dict()[k], v) for k, v in superpoint.items())
    loaded = lg.state_dict()
    assert torch.equal(loaded["transformers.8.cross_attn.to_qk.weight"], lightglue["cross_attn.8.to_qk.weight"])
    assert torch.equal(loaded["transformers.0.self_attn.Wqkv.bias"], lightglue["self_attn.0.Wqkv.bias"])
    assert all(torch.equal(loaded[k], v) for k, v in lightglue.items() if not k.startswith(("self_attn", "cross_attn")))
    assert len(loaded) == len(lightglue) + 1  # + kornia's early-stopping thresholds, computed, not loaded
    kornia_saved = shutil.copytree(folder, tmp_path / "kornia")  # a LightGlue saved from kornia loads too
    torch.save(loaded, kornia_saved / "superpoint_lightglue.pth")
    _, again = load_models(SuperPointLightGlueOptions(weights=str(kornia_saved)))
    assert all(torch.equal(again.state_dict()[k], v) for k, v in loaded.items())


def test_without_weights_the_releases_are_downloaded_once(release, tmp_path, monkeypatch):
    """The download (here a copy of the release-format files, no network) lands in the cache once; the stage
    is then on the official weights, named by their URLs. Offline, the error says how to give them."""
    from vprbench_baselines.lightglue import LIGHTGLUE, SUPERPOINT, SuperPointLightGlueOptions, load_models

    def offline(url, destination, hash_prefix=None, progress=True):
        raise OSError("no network in tests")

    monkeypatch.setattr(torch.hub, "download_url_to_file", offline)
    with pytest.raises(VPRBenchError, match=r"could not download superpoint_v1.pth from https://github.com/magicleap/"
                                            r".*pass it with --rerank-option weights=FOLDER"):
        load_models(SuperPointLightGlueOptions(), cache_dir=tmp_path)

    downloads = []

    def download(url, destination, hash_prefix=None, progress=True):
        downloads.append((url, hash_prefix))
        shutil.copy(release[0] / Path(url).name, destination)

    monkeypatch.setattr(torch.hub, "download_url_to_file", download)
    for _ in range(2):
        superpoint, _ = load_models(SuperPointLightGlueOptions(), cache_dir=tmp_path)
    assert torch.equal(superpoint.state_dict()["convDb.bias"], release[1]["convDb.bias"])
    assert downloads == [(SUPERPOINT.url, None), (LIGHTGLUE.url, None)]  # no sha256 published: none checked
    weights = create_stage(NAME).provenance()["weights"]
    assert weights["source"] == "official"
    assert {name: (part["source"], part["url"], part["release"]) for name, part in weights["files"].items()} == {
        "superpoint_v1.pth": ("official", SUPERPOINT.url, "superpoint"),
        "superpoint_lightglue.pth": ("official", LIGHTGLUE.url, "lightglue")}
    from vprbench.weights import file_sha256, weights_folder
    from vprbench_baselines.lightglue import weights_identities

    assert weights_identities(SuperPointLightGlueOptions(), tmp_path) == {s.file_name: s.url for s in (SUPERPOINT, LIGHTGLUE)}
    by_hand = weights_folder(tmp_path / "by-hand")  # the same bytes put in a cache by hand: the user's files
    shutil.copytree(release[0], by_hand)
    assert weights_identities(SuperPointLightGlueOptions(), tmp_path / "by-hand") == {
        name: f"sha256:{file_sha256(by_hand / name)}" for name in (SUPERPOINT.file_name, LIGHTGLUE.file_name)}


def test_the_weights_folder_is_identified_by_content(release, shared_data, tmp_path):
    folder = release[0]
    moved = shutil.copytree(folder, tmp_path / "elsewhere")

    def spec(weights):
        return resolve_spec("hog", "corridor", stages=[{"name": NAME, "k": 5, "weights": str(weights)}], ks=(1, 5),
                            data_dir=shared_data)

    first = spec(folder)
    assert first.stages[0].options["weights"] == str(folder)  # where to load from, for the run
    assert first.stages[0].identity()["options"]["weights"] == {
        "superpoint_v1.pth": "sha256:" + hashlib.sha256((folder / "superpoint_v1.pth").read_bytes()).hexdigest(),
        "superpoint_lightglue.pth": first.stages[0].files["weights"]["superpoint_lightglue.pth"]}
    assert spec(moved).row_key == first.row_key and first.label() == "hog + superpoint-lightglue@5"
    weights = create_stage(NAME, {"weights": str(moved)}).provenance()["weights"]
    assert weights["source"] == "user" and weights["files"]["superpoint_v1.pth"] == {
        "source": "user", "sha256": first.stages[0].files["weights"]["superpoint_v1.pth"].removeprefix("sha256:")}
    torch.save(release[2] | {"posenc.Wr.weight": torch.zeros(32, 2)}, moved / "superpoint_lightglue.pth")
    assert spec(moved).row_key != first.row_key


def test_corridor_candidates_are_ranked_by_their_matches(release, corridor, tmp_path, monkeypatch):
    """Four queries, three candidates each (the right place last): every score is the number of LightGlue
    matches of the pair, ties keep the order given, and a second run reads every feature from the store."""
    from functools import cache

    from vprbench_baselines import superpoint
    from vprbench_baselines.lightglue import SuperPointLightGlueOptions, load_models

    stage = create_stage(NAME, {"k": 3, "weights": str(release[0]), **SMALL})
    given = Candidates(np.array([[q + 2, q + 1, q] for q in range(4)]), np.zeros((4, 3), np.float32))
    context = StageContext(dataset=corridor, database=None, queries=None, cache_dir=tmp_path)
    found = stage.apply(given, context)
    assert (np.sort(found.indices, 1) == np.sort(given.indices, 1)).all()
    assert (np.diff(found.scores, axis=1) <= 0).all() and (found.scores > 0).any()

    sp, lg = load_models(SuperPointLightGlueOptions(weights=str(release[0]), **SMALL))

    @cache
    def features(path):
        found = superpoint.superpoint_features(sp, load_rgb(path), resize=64, max_keypoints=48, threshold=0.0005,
                                               nms_radius=4)
        return {"keypoints": torch.from_numpy(found["points"])[None],
                "descriptors": torch.from_numpy(found["descriptors"])[None],
                "image_size": torch.from_numpy(found["size"])[None]}

    with torch.inference_mode():
        for q in range(4):
            counts = [len(lg({"image0": features(corridor.queries[q]), "image1": features(corridor.database[row])})
                         ["matches"][0]) for row in given.indices[q]]
            expected = sorted(range(3), key=lambda c: -counts[c])  # stable: equal counts keep the given order
            assert found.indices[q].tolist() == [int(given.indices[q][c]) for c in expected]
            assert found.scores[q].tolist() == [counts[c] for c in expected]

    stored = list(tmp_path.glob("features/superpoint-*/corridor-*/*.h5"))
    assert sorted(p.name for p in stored) == ["database.1.h5", "queries.1.h5"]

    def computed(*args, **kwargs):
        raise AssertionError("a feature was computed again")

    monkeypatch.setattr(superpoint, "superpoint_features", computed)
    again = stage.apply(given, context)
    assert (again.indices == found.indices).all() and (again.scores == found.scores).all()


def test_random_weights_run_is_recorded_as_random_and_fills_no_cell(capsys, shared_data, tmp_path):
    options = [a for key, value in TINY.items() for a in ("--rerank-option", f"{key}={value}")]
    code, out, err = run(capsys, "evaluate", "--method", "hog", "--dataset", "corridor", "--data-dir", shared_data,
                         "--cache-dir", tmp_path, "--k", "1", "--rerank", NAME, "--rerank-k", "1",
                         "--rerank-option", "weights=random", *options, "--json", "--inline-arrays", "--quiet")
    assert code == 0, err
    record = json.loads(out)
    stage = record["stages"][0]
    assert record["track"] == "re-ranked" and stage["name"] == NAME and stage["options"]["weights"] == "random"
    assert stage["provenance"]["weights"] == {"source": "random", "files": {
        "superpoint_v1.pth": {"source": "random"}, "superpoint_lightglue.pth": {"source": "random"}}}
    assert stage["stored_bytes_per_database_image"] > 0

    board = build_board(read_results(tmp_path))
    assert board.cells == {} and [why for r, why in board.excluded] == [RANDOM]

    user = copy.deepcopy(record)  # the same run on the user's files: a row of its own, marked
    user["spec"]["stages"][0]["options"]["weights"] = "/somewhere"
    files = {"superpoint_v1.pth": {"source": "user", "sha256": "ab" * 32},
             "superpoint_lightglue.pth": {"source": "user", "sha256": "cd" * 32}}
    user["stages"][0]["provenance"] = {"weights": {"source": "user", "files": files}}
    (row,) = build_board([user]).rows
    assert not row.official and row.mark == f"{NAME} user weights sha256:{'ab' * 6}, sha256:{'cd' * 6}"


def test_random_weights_are_seeded():
    from vprbench_baselines.lightglue import SuperPointLightGlueOptions, load_models

    first, again = (load_models(SuperPointLightGlueOptions(weights="random")) for _ in range(2))
    for a, b in zip(first, again):
        assert all(torch.equal(a.state_dict()[k], v) for k, v in b.state_dict().items())


@pytest.mark.parametrize("damage, message", [
    ("swap", r"superpoint_lightglue.pth \(LightGlue for SuperPoint, the v0.1 release layout\): the checkpoint does "
             r"not match this architecture \(missing: posenc.Wr.weight, .*unexpected: conv1a.weight"),
    ("drop", r"superpoint_v1.pth \(SuperPoint, Magic Leap's layout\): the checkpoint does not match this "
             r"architecture \(missing: convDb.bias\)"),
    ("text", r"Cannot read weights file .*/superpoint_lightglue.pth: it is damaged or not a PyTorch file.* Give the "
             r"release file superpoint_lightglue.pth in its official format"),
    ("missing", r"superpoint_v1.pth does not exist; download superpoint_v1.pth from https://github.com/magicleap/"),
])
def test_a_file_of_another_format_is_refused_naming_it(release, shared_data, tmp_path, capsys, damage, message):
    folder = shutil.copytree(release[0], tmp_path / "weights")
    if damage == "swap":
        shutil.copy(folder / "superpoint_v1.pth", folder / "superpoint_lightglue.pth")
    elif damage == "drop":
        torch.save({k: v for k, v in release[1].items() if k != "convDb.bias"}, folder / "superpoint_v1.pth")
    elif damage == "text":
        (folder / "superpoint_lightglue.pth").write_text("not weights")
    else:
        (folder / "superpoint_v1.pth").unlink()
    cache = tmp_path / "cache"
    code, _, err = run(capsys, "evaluate", "--method", "hog", "--dataset", "corridor", "--data-dir", shared_data,
                       "--cache-dir", cache, "--rerank", NAME, "--rerank-option", f"weights={folder}")
    assert code == 1 and len(err.strip().splitlines()) == 1
    assert err.startswith(f"error: Stage '{NAME}': ") and re.search(message, err), err
    assert not (cache / "features").exists() and not (cache / "results").exists()  # nothing stored


@pytest.mark.parametrize("option, message", [
    ({"model": "affine"}, "option model: Input should be 'none', 'fundamental' or 'homography'"),
    ({"max_keypoints": 0}, "option max_keypoints: Input should be greater than or equal to 1"),
    # before: accepted, then a traceback allocating 9 TB when the first image was resized
    ({"resize": 1_000_000}, "option resize: Input should be less than or equal to 9459"),
    ({"weights": "{folder}/superpoint_v1.pth"}, "is not a folder; give a folder holding superpoint_v1.pth and "
                                               "superpoint_lightglue.pth"),
])
def test_bad_options_are_refused_when_the_spec_is_made(release, shared_data, option, message):
    option = {k: v.format(folder=release[0]) if isinstance(v, str) else v for k, v in option.items()}
    with pytest.raises(VPRBenchError, match=f"Stage '{NAME}'.*{message}"):
        resolve_spec("hog", "corridor", stages=[{"name": NAME, **option}], data_dir=shared_data)


def nearest_neighbour_lightglue(official_checkpoint) -> dict:
    """LightGlue weights (release layout) that match by SuperPoint descriptors alone: every layer's ffn adds nothing
    (its last linear zero, so descriptors pass through unchanged), the final projection a scaled identity and every
    point matchable, leaving the dual softmax's mutual nearest neighbours. Trained weights need a download; random
    ones are never confident, so they could not tell the true place from another."""
    state = official_checkpoint("lightglue", "superpoint_lightglue", seed=2)
    for key in state:
        if re.fullmatch(r"(self|cross)_attn\.\d+\.ffn\.3\.(weight|bias)", key):
            state[key] = torch.zeros_like(state[key])
        elif re.fullmatch(r"log_assignment\.\d+\.final_proj\.weight", key):
            state[key] = 28 * torch.eye(state[key].shape[0])  # similarities of unit rows x 28^2 / 256^0.5: sharp
        elif re.fullmatch(r"log_assignment\.\d+\.(final_proj|matchability)\.bias", key):
            state[key] = torch.full_like(state[key], 10.0 if "matchability" in key else 0.0)
        elif re.fullmatch(r"log_assignment\.\d+\.matchability\.weight", key):
            state[key] = torch.zeros_like(state[key])
    return state


def test_the_same_place_comes_first_in_any_format(corridor, tmp_path, official_checkpoint):
    """The oracle the other image re-rankers pass (tests/stages/test_stage_oracles.py): queries that are database
    images themselves, in other formats, handed over with the true match last, come out first, by a margin."""
    folder = tmp_path / "weights"
    folder.mkdir()
    torch.save(official_checkpoint("superpoint", "superpoint_v1", seed=1), folder / "superpoint_v1.pth",
               _use_new_zipfile_serialization=False)
    torch.save(nearest_neighbour_lightglue(official_checkpoint), folder / "superpoint_lightglue.pth")
    images = Images([corridor.database[row] for row in PLACES], variants(corridor, tmp_path))
    given = worst_first(len(PLACES))
    stage = create_stage(NAME, {"k": len(PLACES), "weights": str(folder), "resize": 64, "max_keypoints": 48,
                                "depth_confidence": -1, "width_confidence": -1})
    found = stage.apply(given, StageContext(dataset=images, database=None, queries=None, cache_dir=tmp_path / "cache"))
    assert_oracle(given, found)
    assert (found.scores[:, 0] > found.scores[:, 1]).all()  # first by a margin, not by the tie rule


def test_the_record_names_the_libraries_the_matches_come_from():
    """Before: no fingerprint, so after a torch, kornia or OpenCV upgrade a sweep served the old matches, while the
    same run not served computed new SuperPoint features (stored per torch and kornia version)."""
    import cv2
    import kornia

    from vprbench.stages.run import stage_fingerprint

    versions = {"torch": torch.__version__, "kornia": kornia.__version__}
    assert stage_fingerprint(create_stage("superpoint-lightglue", {"weights": "random"})) == versions
    assert stage_fingerprint(create_stage("superpoint-lightglue", {"weights": "random", "model": "homography"})) == \
        {**versions, "opencv": cv2.__version__}
