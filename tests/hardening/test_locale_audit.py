"""A machine whose locale is not UTF-8 (an ASCII "C" locale without coercion, a Windows code page):
vprbench reads its own files as UTF-8 whatever the locale, and writes what the terminal cannot
hold escaped, never a traceback."""
from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
#: Python in the plain ASCII locale: no UTF-8 mode, no coercion of "C" to C.UTF-8
ASCII_LOCALE = {"LC_ALL": "C", "LANG": "C", "PYTHONUTF8": "0", "PYTHONCOERCECLOCALE": "0"}


def vprbench_in_ascii_locale(*args: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONIOENCODING", "LC_CTYPE")}
    # 80 columns whatever the caller's terminal: rich's tables then cut long names with an ellipsis
    return subprocess.run([sys.executable, "-m", "vprbench", *args], capture_output=True, timeout=120,
                          env={**env, **ASCII_LOCALE, "COLUMNS": "80"})


@pytest.mark.parametrize("args", [("methods", "backbones"), ("methods", "list"), ("stages", "list")])
def test_listings_print_in_an_ascii_locale(args):
    """Before: the backbone manifests (a name with an accent in a comment) failed to decode, and
    rich's '…' failed to encode: UnicodeDecodeError / UnicodeEncodeError tracebacks, exit 1."""
    done = vprbench_in_ascii_locale(*args)
    assert done.returncode == 0, done.stderr.decode("ascii", "replace")[-600:]
    assert b"Traceback" not in done.stderr
    out = done.stdout.decode("ascii")  # nothing but ASCII reached the terminal
    assert "\\u2026" in out  # the table's ellipsis, escaped rather than dropped
    if args == ("methods", "backbones"):
        assert "dinov3" in out


def test_a_manifest_is_read_as_utf8_whatever_the_locale():
    """The accent in the DINOv3 manifest's comment is what an ASCII decode failed on."""
    code = ("import locale; assert locale.getpreferredencoding(False).lower() in ('ansi_x3.4-1968', 'ascii'); "
            "from vprbench.features.catalogue import backbones; print(sorted(backbones())[0])")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONIOENCODING"}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                          env={**env, **ASCII_LOCALE})
    assert done.returncode == 0, done.stderr[-600:]
    assert "é".encode() in (ROOT / "manifests" / "backbones" / "dinov3.toml").read_bytes()


TEXT_CALLS = {"read_text", "write_text"}


def _unspecified_encodings(path: Path) -> list[str]:
    """Calls that read or write text in the locale's encoding: Path.read_text/write_text, open()
    or Path.open() in a text mode, subprocess with text=True, each without encoding=."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if not isinstance(node, ast.Call):
            continue
        keywords = {k.arg: k.value for k in node.keywords}
        if "encoding" in keywords:
            continue
        name = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", None)
        mode = keywords.get("mode")
        if name == "open" and mode is None:
            positional = node.args[1:2] if isinstance(node.func, ast.Name) else node.args[0:1]
            mode = positional[0] if positional else None
        text_mode = not (isinstance(mode, ast.Constant) and isinstance(mode.value, str) and "b" in mode.value)
        is_text_open = name == "open" and text_mode and not (
            isinstance(node.func, ast.Attribute) and isinstance(node.func.value, ast.Name)
            and node.func.value.id in {"os", "h5py", "tarfile", "zipfile", "Image", "archive"})
        text_true = any(k in keywords and isinstance(keywords[k], ast.Constant) and keywords[k].value is True
                        for k in ("text", "universal_newlines"))
        if name in TEXT_CALLS or is_text_open or text_true:
            found.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    return found


def test_every_text_read_and_write_names_its_encoding():
    """So a file vprbench ships or writes reads the same on every machine (the locale's encoding
    is ASCII in a bare "C" locale and a code page on Windows)."""
    sources = sorted((ROOT / "vprbench").rglob("*.py")) + sorted((ROOT / "baselines").rglob("*.py"))
    found = [where for path in sources for where in _unspecified_encodings(path)]
    assert found == []


def test_the_check_finds_what_it_looks_for(tmp_path, monkeypatch):
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    source = tmp_path / "m.py"
    source.write_text("p.read_text()\nopen(p)\nopen(p, 'w')\nsubprocess.run(c, text=True)\np.open('r')\n"
                      "p.read_text(encoding='utf-8')\nopen(p, 'rb')\np.open('ab')\nos.open(p, 1)\n", encoding="utf-8")
    assert _unspecified_encodings(source) == [f"m.py:{n}" for n in (1, 2, 3, 4, 5)]
