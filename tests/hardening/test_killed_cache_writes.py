"""Caches other than descriptor stores after a kill -9: the rerun leaves one whole entry and no
temporary file of the killed writer, even one younger than the hour after which strays are swept."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import torch

from vprbench.aggregation.vocabulary import Vocabulary, load_vocabulary
from vprbench.methods.anyloc_vocabulary import save_to_cache

SETTING = ("dino_vits8@random", 1, "value")

#: saves a vocabulary into the cache and is killed (SIGKILL) just before its temporary file is renamed in place
KILLED_SAVE = """
import os, signal, sys, torch
from vprbench.aggregation.vocabulary import Vocabulary
from vprbench.methods.anyloc_vocabulary import save_to_cache
os.replace = lambda *args: os.kill(os.getpid(), signal.SIGKILL)
save_to_cache(Vocabulary(torch.zeros(4, 8), {}), "dino_vits8@random", 1, "value", "mine", sys.argv[1])
"""


def test_a_save_into_the_cache_removes_a_killed_saves_temporary_file(tmp_path):
    """Was: the killed save's `.vocabulary.pt.*.tmp` stayed for an hour after the rerun (a live save's
    could not be told from it); saves of one key now take turns, so any found then is a dead one's."""
    killed = subprocess.run([sys.executable, "-c", KILLED_SAVE, str(tmp_path)], capture_output=True, text=True,
                            timeout=60)
    assert killed.returncode == -9, killed.stderr
    folder = tmp_path / "vocabularies" / "dino_vits8@random-l1-value-c4" / "mine"
    assert len([p for p in folder.iterdir() if p.name.endswith(".tmp")]) == 1  # the killed save's
    centres = torch.arange(32, dtype=torch.float32).reshape(4, 8)
    path = save_to_cache(Vocabulary(centres, {}), *SETTING, "mine", tmp_path)
    assert sorted(p.name for p in folder.iterdir()) == [".vocabulary.pt.lock", "vocabulary.pt"]
    assert torch.equal(load_vocabulary(path).centres, centres)


#: `vprbench ARGS...` killed (SIGKILL) once its new leaderboard section is written, before it is swapped in
KILLED_PUBLISH = """
import os, signal, sys
from vprbench.cli.main import main
from vprbench.leaderboard import site

def killed(*args, **kwargs):
    written(*args, **kwargs)
    os.kill(os.getpid(), signal.SIGKILL)

written, site.write_section = site.write_section, killed
sys.exit(main(sys.argv[1:]))
"""


def test_a_publish_removes_what_a_killed_publish_left(shared_data, tmp_path, cli):
    """Was: the killed publish's `.leaderboard-new-*` folder (a whole site) stayed beside the section for
    an hour after the next publish; a publish now holds a lock on its own, so a dead one's is known."""
    from vprbench.evaluation import evaluate, save_result
    from vprbench.spec import RunSettings, resolve_spec

    cache = tmp_path / "cache"
    spec = resolve_spec("hog", "corridor", options={"resize": [32, 32]}, data_dir=shared_data, cache_dir=cache)
    save_result(evaluate(spec, RunSettings(cache_dir=cache, data_dir=shared_data, workers=0)), cache)
    docs = tmp_path / "docs"
    args = ["leaderboard", "publish", "--to", docs, "--cache-dir", cache]
    killed = subprocess.run([sys.executable, "-c", KILLED_PUBLISH, *map(str, args)], capture_output=True, text=True,
                            timeout=120)
    assert killed.returncode == -9, killed.stderr
    assert any(p.is_dir() and p.name.startswith(".leaderboard-new-") for p in docs.iterdir())
    code, _, err = cli(*args)
    assert code == 0 and "Traceback" not in err, err
    assert sorted(p.name for p in docs.iterdir()) == [".leaderboard.lock", ".leaderboard.read-at", "leaderboard"]
    assert (docs / "leaderboard" / "index.md").is_file()


#: downloads weights (a file:// release, no network needed) into the cache, killed before its '.partial' file is moved in
KILLED_DOWNLOAD = """
import os, shutil, signal, sys
from vprbench.weight_source import WeightSource
from vprbench.weights import resolve_weights
shutil.move = lambda *args: os.kill(os.getpid(), signal.SIGKILL)
resolve_weights(WeightSource("w.pth", url=sys.argv[1]), None, "test", cache_dir=sys.argv[2])
"""


def test_a_download_removes_what_a_killed_download_left(tmp_path):
    """Was: torch's `w.pth.<hex>.partial` of a killed download stayed in the cache for good."""
    from vprbench.fsutil import file_sha256
    from vprbench.weight_source import WeightSource
    from vprbench.weights import resolve_weights, weights_folder

    release = tmp_path / "release.pth"
    torch.save({"w": torch.arange(1000.0)}, release)
    cache = tmp_path / "cache"
    killed = subprocess.run([sys.executable, "-c", KILLED_DOWNLOAD, release.as_uri(), str(cache)],
                            capture_output=True, text=True, timeout=60)
    assert killed.returncode == -9, killed.stderr
    folder = weights_folder(cache)
    assert len(list(folder.glob("w.pth.*.partial"))) == 1
    found = resolve_weights(WeightSource("w.pth", url=release.as_uri()), None, "test", cache_dir=cache).path
    assert found == folder / "w.pth" and file_sha256(found) == file_sha256(release)
    assert sorted(p.name for p in folder.iterdir()) == [".w.pth.lock", "w.pth"]


#: fits PCA-whitening on seeded rows and saves its state in a folder, killed (SIGKILL) just before the rename
KILLED_STATE = """
import os, signal, sys
import numpy as np
from vprbench.aggregation.pca import PCAWhitening
from vprbench.evaluation.postprocess import fit_postprocessor
from vprbench.row_sources import ArrayRows
rows = ArrayRows(np.random.default_rng(0).standard_normal((64, 16)).astype(np.float32))
os.replace = lambda *args: os.kill(os.getpid(), signal.SIGKILL)
fit_postprocessor(PCAWhitening(8), rows, 2**28, state_folder=sys.argv[1])
"""


def test_a_saved_post_processing_state_removes_what_killed_saves_left(tmp_path):
    """Was: each evaluation killed while saving its PCA state left a `.postprocess-*.npz.*.tmp` (the
    state's size) in the store folder for good: nothing ever removed them."""
    import numpy as np

    from vprbench.aggregation.pca import PCAWhitening
    from vprbench.evaluation.postprocess import fit_postprocessor
    from vprbench.row_sources import ArrayRows

    for _ in range(2):
        killed = subprocess.run([sys.executable, "-c", KILLED_STATE, str(tmp_path)], capture_output=True, text=True,
                                timeout=60)
        assert killed.returncode == -9, killed.stderr
    assert len([p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]) == 2
    rows = np.random.default_rng(0).standard_normal((64, 16)).astype(np.float32)
    fitted = PCAWhitening(8)
    info = fit_postprocessor(fitted, ArrayRows(rows), 2**28, state_folder=tmp_path)
    name = Path(info["file"]).name
    assert info["state"] == "fitted" and sorted(p.name for p in tmp_path.iterdir()) == [f".{name}.lock", name]
    loaded = PCAWhitening(8)
    assert fit_postprocessor(loaded, ArrayRows(rows), 2**28, state_folder=tmp_path)["state"] == "loaded"
    np.testing.assert_array_equal(loaded.transform(rows), fitted.transform(rows))


#: claims a sweep's cell, killed (SIGKILL) just before its lease file is renamed in place
KILLED_CLAIM = """
import os, signal, sys
from vprbench.sweep.claims import Claims
claims = Claims(sys.argv[1])
os.replace = lambda *args: os.kill(os.getpid(), signal.SIGKILL)
claims.claim("cell", lambda: False)
"""


def test_a_claim_removes_what_killed_claims_of_its_cell_left(tmp_path):
    """Was: each `vprbench run` killed while writing a lease (or failure marker) left a
    `.<cell>.lease.*.tmp` under sweeps/claims for good: nothing ever removed them."""
    from vprbench.sweep.claims import Claims

    for _ in range(2):
        killed = subprocess.run([sys.executable, "-c", KILLED_CLAIM, str(tmp_path)], capture_output=True, text=True,
                                timeout=60)
        assert killed.returncode == -9, killed.stderr
    folder = tmp_path / "sweeps" / "claims"
    assert len([p for p in folder.iterdir() if p.name.endswith(".tmp")]) == 2
    claims = Claims(tmp_path)
    try:
        assert claims.claim("cell", lambda: False) == ("claimed", "")
        assert sorted(p.name for p in folder.iterdir()) == ["cell.alive", "cell.lease", "cell.lock"]
        claims.release("cell", "it failed")
        assert sorted(p.name for p in folder.iterdir()) == ["cell.failed", "cell.lock"]
    finally:
        claims.close()


#: `vprbench ARGS...` killed (SIGKILL) just before the temporary of its output (`--out`, the last
#: argument but one) is renamed in place
KILLED_OUTPUT = """
import os, signal, sys
from vprbench.cli.main import main
replace = os.replace
def killed(source, target, *args, **kwargs):
    if str(target) == sys.argv[-2]:
        os.kill(os.getpid(), signal.SIGKILL)
    return replace(source, target, *args, **kwargs)
os.replace = killed
sys.exit(main(sys.argv[1:]))
"""


def test_an_output_written_again_removes_what_a_killed_write_of_it_left(shared_data, tmp_path, cli):
    """`describe --out` (as `results export --to`, any file written whole): was: the killed write's
    `.d.npy.*.tmp` stayed beside the output for good. The next write of that file removes it once
    untouched for an hour (a live writer's, e.g. a second describe to the same file, is younger)."""
    import os
    import time

    import numpy as np

    out, image = tmp_path / "out" / "d.npy", shared_data / "corridor" / "query" / "0000000.jpg"
    out.parent.mkdir()
    args = ["describe", "--method", "hog", "--resize", "32", "32", "--cache-dir", str(tmp_path / "cache"),
            "--out", str(out), str(image)]
    killed = subprocess.run([sys.executable, "-c", KILLED_OUTPUT, *args], capture_output=True, text=True, timeout=120)
    assert killed.returncode == -9, killed.stderr
    [left] = [p for p in out.parent.iterdir() if p.name.endswith(".tmp")]
    hours_ago = time.time() - 2 * 3600
    os.utime(left, (hours_ago, hours_ago))
    live = out.parent / ".d.npy.live.tmp"
    live.write_bytes(b"half a file")
    assert cli(*args)[0] == 0
    assert sorted(p.name for p in out.parent.iterdir()) == [live.name, "d.npy"]
    assert np.load(out).shape[0] == 1


#: makes dense-vlad fit a vocabulary on a folder of images into the cache, killed (SIGKILL) just before the
#: fitted file is renamed in place
KILLED_DENSE_VLAD_FIT = """
import os, signal, sys
import vprbench
replace = os.replace
def killed(source, target, *args, **kwargs):
    if str(target).endswith("vocabulary.pt"):
        os.kill(os.getpid(), signal.SIGKILL)
    return replace(source, target, *args, **kwargs)
os.replace = killed
vprbench.create_method("dense-vlad", clusters=8, bin_sizes=(6,), step=8, vocabulary=sys.argv[2],
                       cache_dir=sys.argv[1]).fingerprint()  # its vocabulary's centres: fitted now
"""


def test_a_dense_vlad_vocabulary_fitted_again_removes_what_killed_fits_left(shared_data, tmp_path):
    """Was: each dense-vlad run killed while saving the vocabulary it fitted into the cache left a
    `.vocabulary.pt.*.tmp` (the vocabulary's size) beside it for good: the fit after it kept them."""
    import shutil

    import vprbench

    images, cache = tmp_path / "images", tmp_path / "cache"
    images.mkdir()
    for path in sorted((shared_data / "corridor" / "ref").glob("*.jpg"))[:3]:
        shutil.copyfile(path, images / path.name)
    for _ in range(2):
        killed = subprocess.run([sys.executable, "-c", KILLED_DENSE_VLAD_FIT, str(cache), str(images)],
                                capture_output=True, text=True, timeout=120)
        assert killed.returncode == -9, killed.stderr
    [folder] = (cache / "vocabularies" / "dense-vlad").iterdir()
    assert len([p for p in folder.iterdir() if p.name.endswith(".tmp")]) == 2
    method = vprbench.create_method("dense-vlad", clusters=8, bin_sizes=(6,), step=8, vocabulary=str(images),
                                    cache_dir=cache)
    assert method.fingerprint()["vocabulary"].startswith("sha256:")  # fitted (once more) and saved
    assert sorted(p.name for p in folder.iterdir()) == [".fit.lock", "vocabulary.pt"]
    assert load_vocabulary(folder / "vocabulary.pt").centres.shape == (8, 128)
