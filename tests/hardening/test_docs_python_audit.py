"""The Python a researcher copies from the docs runs as written, and does what the text around it says."""
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

#: every ```python block of README.md and docs/*.md (page, its first line) -> the test that runs it, or why none can
BLOCKS = {
    ("add-your-method.md", 'vprbench.register_method("thumbnail", Thumbnail, defaults={"size": 16}, '
                           'description="grey 16x16 thumbnail")'):
        "test_the_register_line_of_add_your_method_md_registers_the_pages_thumbnail",
    ("add-your-method.md", '"""A method living outside vprbench: grey thumbnails, mean-centred, as global descriptors."""'):
        "tests/baselines/test_plugin_beside_baselines.py (the example folder's file, installed and evaluated)",
    ("add-your-method.md", "from vprbench_baselines.common import ("):
        "test_the_weights_snippet_of_add_your_method_md_loads_a_checkpoint (its MyNet is the reader's: a tiny one)",
    ("runs.md", "from vprbench.evaluation import evaluate, save_result"):
        "tests/hardening/test_docs_commands_audit.py::test_the_python_snippet_of_runs_md_runs_as_written",
    ("stages.md", "import numpy as np"):
        "tests/hardening/test_docs_commands_audit.py::test_the_stage_snippet_of_stages_md_defines_a_stage",
}


def _blocks(page: str) -> list[str]:
    path = ROOT / ("README.md" if page == "README.md" else f"docs/{page}")
    return re.findall(r"```python\n(.*?)```", path.read_text(), flags=re.S)


def _block(page: str, start: str) -> str:
    (found,) = [b for b in _blocks(page) if b.startswith(start)]
    return found


def test_every_python_block_of_the_docs_is_run_by_a_test():
    # a block added or edited without its test is one nobody ran
    pages = ["README.md", *sorted(p.name for p in (ROOT / "docs").glob("*.md"))]
    found = {(page, block.splitlines()[0]) for page in pages for block in _blocks(page)}
    assert found == set(BLOCKS), (found - set(BLOCKS), set(BLOCKS) - found)
    # and each test named runs: a renamed or deleted one would leave its block unrun while this still passed
    for where in BLOCKS.values():
        named = where.split(" ")[0]
        path, _, name = named.partition("::") if named.startswith("tests/") else (__file__, "", named)
        assert (ROOT / path).is_file() and (not name or f"def {name}(" in (ROOT / path).read_text()), where


def test_the_register_line_of_add_your_method_md_registers_the_pages_thumbnail(scratch_methods):
    # docs/add-your-method.md: the line, run beside section 2's Thumbnail, makes the preset it describes
    # (it showed defaults={...}: a set, refused with a ValueError)
    import vprbench
    from vprbench.methods import registry

    scope: dict = {}
    exec(compile(_block("add-your-method.md", '"""A method living'), "docs/add-your-method.md", "exec"), scope)
    line = _block("add-your-method.md", 'vprbench.register_method("thumbnail", Thumbnail,')
    exec(compile("import vprbench\n" + line, "docs/add-your-method.md", "exec"), scope)
    method = vprbench.create_method("thumbnail")
    assert isinstance(method, scope["Thumbnail"]) and method.size == 16
    assert registry.method_entry("thumbnail").defaults == {"size": 16}


def test_the_weights_snippet_of_add_your_method_md_loads_a_checkpoint(shared_data, tmp_path, monkeypatch):
    # docs/add-your-method.md "5. Weights": with the reader's network (here a tiny random one) in my_package,
    # --weights PATH is loaded by exact keys, identified by its sha256, and describes images as unit rows
    import numpy as np
    import torch

    package = tmp_path / "site" / "my_package"
    package.mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "network.py").write_text(
        "import torch\n\n\nclass MyNet(torch.nn.Module):\n    def __init__(self):\n        super().__init__()\n"
        "        self.conv = torch.nn.Conv2d(3, 8, 3, stride=2)\n        self.fc = torch.nn.Linear(8, 512)\n\n"
        "    def forward(self, x):\n        return self.fc(self.conv(x).mean(dim=(2, 3)))\n")
    monkeypatch.syspath_prepend(str(tmp_path / "site"))
    scope: dict = {}
    exec(compile(_block("add-your-method.md", "from vprbench_baselines.common import ("), "docs/add-your-method.md",
                 "exec"), scope)
    torch.manual_seed(0)
    torch.save(scope["MyNet"]().state_dict(), tmp_path / "my_net_512.pth")
    method = scope["my_net"](weights=str(tmp_path / "my_net_512.pth"), resize=(32, 32), cache_dir=tmp_path)
    assert method.provenance()["weights"]["source"] == "user"
    assert method.fingerprint()["architecture"] == "my-net" and len(method.fingerprint()["weights_sha256"]) == 64
    images = sorted(str(p) for p in (shared_data / "corridor" / "query").glob("*.jpg"))[:2]
    rows = method.describe(images)
    assert rows.shape == (2, 512) and rows.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(rows, axis=1), 1.0, atol=1e-5)


def test_the_leaderboard_calls_of_leaderboard_guide_md_do_what_it_says(shared_data, tmp_path):
    # docs/leaderboard-guide.md "From Python": every name the sentence calls is vprbench.leaderboard's (truth_note and
    # LocalTruth were only in vprbench.leaderboard.truth), and build_board re-scores only when given the truth
    import warnings

    import vprbench.leaderboard
    from vprbench.evaluation import evaluate, read_results, save_result
    from vprbench.spec import RunSettings, resolve_spec

    text = " ".join((ROOT / "docs" / "leaderboard-guide.md").read_text().split())
    sentence = re.search(r"From Python, (.*?)\.(?: |$)(?=[A-Z])", text).group(1)
    called = set(re.findall(r"`(?:vprbench\.leaderboard\.)?(?:truth=)?(\w+)\(", sentence))
    assert called == {"leaderboard", "build_board", "LocalTruth", "truth_note"}, sentence
    assert not [name for name in called if not hasattr(vprbench.leaderboard, name)]

    spec = resolve_spec("hog", "corridor", options={"resize": [32, 32]}, ks=(1, 5))
    save_result(evaluate(spec, RunSettings(data_dir=shared_data, cache_dir=tmp_path)), tmp_path)
    records = read_results(tmp_path)
    board = vprbench.leaderboard.build_board(records)
    assert "1 of 1 cell(s) were NOT re-scored" in vprbench.leaderboard.truth_note(board)
    board = vprbench.leaderboard.build_board(records, truth=vprbench.leaderboard.LocalTruth(shared_data))
    assert vprbench.leaderboard.truth_note(board).startswith("Every cell was re-scored")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # every cell re-scored: nothing to warn of
        table = vprbench.leaderboard.leaderboard(records, shared_data)
    assert table.attrs["truth_note"].startswith("Every cell was re-scored")


def test_every_object_the_api_reference_renders_has_its_own_docstring():
    # docs/api.md renders these with mkdocstrings; RunSpec had none, so help() showed pydantic's BaseModel text
    import importlib

    missing = []
    for target in re.findall(r"^::: (\S+)", (ROOT / "docs" / "api.md").read_text(), flags=re.M):
        try:
            obj = importlib.import_module(target)
        except ImportError:
            module, name = target.rsplit(".", 1)
            obj = getattr(importlib.import_module(module), name)
        own = vars(obj).get("__doc__") if isinstance(obj, type) else obj.__doc__
        if not (own or "").strip():
            missing.append(target)
    assert not missing, missing


def test_every_vprbench_function_the_docs_name_by_path_exists():
    # `vprbench.x.y(...)` in the text is a call a reader types: each must resolve as written
    import importlib

    missing = []
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for dotted in sorted(set(re.findall(r"`(vprbench(?:\.\w+)+)\(", path.read_text()))):
            module, name = dotted.rsplit(".", 1)
            try:
                getattr(importlib.import_module(module), name)
            except (ImportError, AttributeError):
                missing.append(f"{path.name}: {dotted}")
    assert not missing, missing
