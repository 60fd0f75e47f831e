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


# ---------------------------------------------------------------- the one resolver
from pathlib import Path  # noqa: E402

from vprbench.weight_source import WeightSource  # noqa: E402
from vprbench.weights import resolve_weights, weights_identity, weights_provenance  # noqa: E402


def _refuse_network(monkeypatch):
    import huggingface_hub

    def refuse(*args, **kwargs):
        raise OSError("no network in tests")

    monkeypatch.setattr(torch.hub, "download_url_to_file", refuse)
    monkeypatch.setattr(huggingface_hub, "hf_hub_download", refuse)
    monkeypatch.setattr(huggingface_hub, "get_hf_file_metadata", refuse)


def test_local_file_or_folder_is_identified_by_its_sha256(tmp_path):
    path = tmp_path / "w.pth"
    torch.save({"a": torch.ones(1)}, path)
    source = WeightSource("w.pth", url="https://example.org/w.pth")
    for given in (path, tmp_path, str(path)):  # a folder holding the release's file name gives that file
        found = resolve_weights(source, given, "toy")
        assert found.path == path and found.identity == "sha256:" + file_sha256(path)
    assert weights_identity(source, tmp_path, "toy") == "sha256:" + file_sha256(path)
    with pytest.raises(VPRBenchError, match=r"toy: weights file .*nope\.pth does not exist; download w\.pth from "
                                            r"https://example\.org/w\.pth and pass it with --weights PATH"):
        resolve_weights(source, tmp_path / "nope.pth", "toy")


def test_release_url_downloads_once_into_the_cache_given_checked_by_its_sha256(tmp_path, monkeypatch):
    calls = []

    def fake(url, destination, hash_prefix=None, progress=True):
        calls.append((url, hash_prefix))
        torch.save({"a": torch.ones(1)}, destination)

    monkeypatch.setattr(torch.hub, "download_url_to_file", fake)
    source = WeightSource("w.pth", url="https://example.org/w.pth", sha256="cd" * 32)
    first = resolve_weights(source, None, "toy", cache_dir=tmp_path / "c")
    again = resolve_weights(source, None, "toy", cache_dir=tmp_path / "c")
    assert first == again and first.identity == "https://example.org/w.pth"
    assert first.path == tmp_path / "c" / "torch" / "hub" / "checkpoints" / "w.pth"
    assert calls == [("https://example.org/w.pth", "cd" * 32)]  # torch checks the published sha256 prefix


def test_hub_file_downloads_into_the_cache_given(tmp_path, monkeypatch):
    import huggingface_hub

    calls = []

    def fake(repo_id, filename, cache_dir=None, **kwargs):
        calls.append((repo_id, filename, cache_dir))
        path = Path(cache_dir) / "x" / filename
        path.parent.mkdir(parents=True, exist_ok=True)
        torch.save({"a": torch.ones(1)}, path)
        return str(path)

    monkeypatch.setattr(huggingface_hub, "hf_hub_download", fake)
    monkeypatch.setattr(huggingface_hub, "get_hf_file_metadata", lambda url, **kwargs: None)
    source = WeightSource("model.safetensors", hub="org/model")
    found = resolve_weights(source, None, "toy", cache_dir=tmp_path / "c")
    assert found.identity == "hf:org/model/model.safetensors" == weights_identity(source, None, "toy")
    assert calls == [("org/model", "model.safetensors", str(tmp_path / "c" / "huggingface"))]
    assert weights_provenance(found.identity) == {"source": "official", "hub": "org/model", "file": "model.safetensors",
                                                  "recognised_by": "download"}


def test_offline_or_page_only_says_how_to_supply(tmp_path, monkeypatch):
    _refuse_network(monkeypatch)
    with pytest.raises(VPRBenchError, match=r"toy: could not download w\.pth from https://example\.org/w\.pth "
                                            r"\(no network in tests\)\. Offline\? download w\.pth"):
        resolve_weights(WeightSource("w.pth", url="https://example.org/w.pth"), None, "toy", cache_dir=tmp_path)
    with pytest.raises(VPRBenchError, match=r"could not download m\.bin from https://huggingface\.co/org/m"):
        resolve_weights(WeightSource("m.bin", hub="org/m"), None, "toy", cache_dir=tmp_path)
    with pytest.raises(VPRBenchError, match=r"toy: the authors publish m\.ckpt only at https://drive\.example/m, "
                                            r"which cannot be downloaded automatically"):
        resolve_weights(WeightSource("m.ckpt", page="https://drive.example/m"), None, "toy", cache_dir=tmp_path)


def test_gated_or_unreachable_hub_weights_are_one_line_at_once(shared_data, tmp_path, monkeypatch, capsys):
    """Evaluating a gated backbone without access (or offline) fails on the hub's first answer, with
    one line: where to request access and how to pass a local file. The hub client's retries never
    run, and no result is stored."""
    import time

    import huggingface_hub
    from huggingface_hub.errors import GatedRepoError

    from vprbench.cli.main import main

    def gated(url, **kwargs):  # what the hub answers a user without access
        assert kwargs.get("retry_on_errors") is False
        import httpx2

        response = httpx2.Response(401, request=httpx2.Request("HEAD", url))
        raise GatedRepoError("401 Client Error: access to model timm/x is restricted", response=response)

    def never(*args, **kwargs):
        raise AssertionError("downloaded after the first answer")

    monkeypatch.setattr(huggingface_hub, "hf_hub_download", never)
    args = ["evaluate", "--method", "anyloc", "--backbone", "dinov3_vits16", "--layer", "9", "--aggregation", "gem",
            "--dataset", "corridor", "--data-dir", str(shared_data), "--cache-dir", str(tmp_path / "cache")]
    for probe, said in ((gated, "the weights are gated (DINOv3 License): request access at "
                                "https://huggingface.co/timm/vit_small_patch16_dinov3.lvd1689m and log in"),
                        (huggingface_hub.get_hf_file_metadata, "Offline? download model.safetensors")):
        if probe is gated:
            monkeypatch.setattr(huggingface_hub, "get_hf_file_metadata", gated)
        else:
            monkeypatch.undo()
            monkeypatch.setattr(huggingface_hub, "hf_hub_download", never)
            monkeypatch.setattr(huggingface_hub, "get_hf_file_metadata", _unreachable)
        start = time.perf_counter()
        assert main(args) == 1
        assert time.perf_counter() - start < 30  # no retries: seconds, as the run's own start-up
        err = capsys.readouterr().err.strip().splitlines()
        error = [line for line in err if line.startswith("error:")]
        assert len(error) == 1 and said in error[0] and "--weights PATH" in error[0], err
        assert "Traceback" not in "\n".join(err)
    assert not list((tmp_path / "cache").rglob("*.json"))  # no result recorded


def _unreachable(url, **kwargs):
    assert kwargs.get("retry_on_errors") is False
    raise OSError("[Errno -2] Name or service not known")


def test_evaluate_reads_weights_from_the_run_settings_cache(shared_data, tmp_path, monkeypatch):
    """`evaluate(spec, RunSettings(cache_dir=X))` finds the backbone's release file in X, not in
    the default cache (which stays empty), and downloads nothing."""
    from vprbench.datasets import load_dataset
    from vprbench.evaluation import evaluate
    from vprbench.features.backbones import backbone_spec, create_model
    from release_formats import official_state_dict
    from vprbench.paths import default_cache
    from vprbench.spec import RunSettings, resolve_spec

    _refuse_network(monkeypatch)
    torch.manual_seed(0)
    backbone = backbone_spec("dinov2_vits14")
    cache = tmp_path / "X"
    release = cache / "torch" / "hub" / "checkpoints" / backbone.file_name
    state = official_state_dict(create_model(backbone), backbone)
    monkeypatch.setattr(torch.hub, "download_url_to_file", lambda url, to, **kwargs: torch.save(state, to))
    resolve_weights(backbone.source, None, "toy", cache_dir=cache)  # downloaded by vprbench (not put there by hand)
    _refuse_network(monkeypatch)
    dataset = load_dataset("corridor", shared_data)
    spec = resolve_spec("anyloc", dataset, options={"backbone": "dinov2_vits14", "layer": 0, "aggregation": "gem",
                                                    "resize": "28x28"})
    record = evaluate(spec, RunSettings(cache_dir=cache), dataset=dataset)
    assert record["provenance"]["weights"] == {"source": "official", "url": backbone.url, "recognised_by": "download",
                                               "release": "dinov2", "sha256": file_sha256(release)}
    assert record["descriptor_dim"] == 384
    assert not list(default_cache().rglob(backbone.file_name))
    with pytest.raises(VPRBenchError, match=r"could not download dinov2_vits14_pretrain\.pth .*no network"):
        evaluate(spec, RunSettings(cache_dir=tmp_path / "empty"), dataset=dataset)


def test_a_folder_of_release_files_may_hold_one_under_the_authors_script_name(tmp_path, monkeypatch):
    """Patch-NetVLAD's download script saves the hub's pitts_WPCA4096.pth.tar as
    pittsburgh_WPCA4096.pth.tar: such a folder, given as --weights, was refused ('does not exist')."""
    from vprbench.weights import local_weights
    from vprbench_baselines import netvlad

    given = {}
    monkeypatch.setattr(netvlad, "load_checkpoint", lambda weights, source, *a: (given.update(source=source), ({}, {}))[1])
    monkeypatch.setattr(netvlad, "build_loaded", lambda build, state, name: torch.nn.Identity())
    netvlad.netvlad_vgg16(dim=512)
    source = given["source"]
    assert (source.file_name, source.also_named) == ("pitts_WPCA512.pth.tar", ("pittsburgh_WPCA512.pth.tar",))
    (tmp_path / "pittsburgh_WPCA512.pth.tar").write_bytes(b"x")
    assert local_weights(source, tmp_path, "netvlad-vgg16") == tmp_path / "pittsburgh_WPCA512.pth.tar"
    (tmp_path / "pitts_WPCA512.pth.tar").write_bytes(b"y")  # the release's own name first
    assert local_weights(source, tmp_path, "netvlad-vgg16") == tmp_path / "pitts_WPCA512.pth.tar"
    (tmp_path / "empty").mkdir()
    with pytest.raises(VPRBenchError, match=r"weights file .*/empty/pitts_WPCA512.pth.tar does not exist"):
        local_weights(source, tmp_path / "empty", "netvlad-vgg16")


@pytest.mark.parametrize("given", ["", "  "])
def test_weights_that_name_no_file_are_refused_not_read_from_the_working_folder(tmp_path, monkeypatch, given):
    """--weights '' (an unset shell variable) was Path(''), the working folder: its copy of the release was loaded."""
    from vprbench.weight_source import WeightSource
    from vprbench.weights import local_weights, resolve_weights

    source = WeightSource("w.pth", url="https://example.org/w.pth")
    (tmp_path / "w.pth").write_bytes(b"x")
    monkeypatch.chdir(tmp_path)
    for call in (lambda: local_weights(source, given, "toy"), lambda: resolve_weights(source, given, "toy", cache_dir=tmp_path)):
        with pytest.raises(VPRBenchError, match=rf"^toy: --weights '{given}' names no file: give a weights file"):
            call()
