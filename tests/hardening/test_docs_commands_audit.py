"""What a researcher reads is right: claims of the docs checked against what the code does."""
import pytest
import torch

from vprbench.aggregation.vocabulary import Vocabulary, vocabulary_dir


def _cached(tmp_path, source: str, datasets: dict) -> None:
    """A vocabulary as `vprbench vocabulary fit` leaves it: its meta names the datasets it saw."""
    folder = vocabulary_dir("dinov2_vits14@random", 3, "value", 4, source, tmp_path)
    meta = {"backbone": "dinov2_vits14@random", "layer": 3, "facet": "value", "stride": 14, "clusters": 4,
            "source": source, "datasets": datasets}
    Vocabulary(torch.nn.functional.normalize(torch.randn(4, 384, generator=torch.Generator().manual_seed(0)), dim=1),
               meta).save(folder / "vocabulary.pt")


def _anyloc(tmp_path, vocabulary: str):
    from vprbench import create_method

    return create_method("anyloc", backbone="dinov2_vits14", weights="random", layer=3, clusters=4,
                         vocabulary=vocabulary, cache_dir=tmp_path)


@pytest.mark.parametrize("source, datasets, seen, unseen", [
    ("map-corridor", {"corridor": 111}, "corridor", "baidu-mall"),
    ("indoor", {"gardens-point": 200, "17places": 406, "baidu-mall": 689}, "baidu-mall", "corridor"),
])
def test_a_cached_vocabulary_fitted_on_the_evaluated_database_says_so(tmp_path, source, datasets, seen, unseen):
    # docs/anyloc.md: the record says whether the vocabulary was fitted on the evaluated database;
    # `vocabulary fit --dataset corridor` then `--vocabulary map-corridor` on corridor is that case
    _cached(tmp_path, source, datasets)
    method = _anyloc(tmp_path, source)
    method.use_dataset(seen)
    found = method.provenance()["vocabulary"]
    assert found["fitted_on_evaluated_database"] is True
    assert seen in found["fitted_on"]
    method.use_dataset(unseen)  # the same centres never saw this dataset
    assert method.provenance()["vocabulary"]["fitted_on_evaluated_database"] is False


def test_a_vocabulary_file_fitted_on_the_evaluated_database_says_so(tmp_path):
    _cached(tmp_path, "map-corridor", {"corridor": 111})
    path = vocabulary_dir("dinov2_vits14@random", 3, "value", 4, "map-corridor", tmp_path) / "vocabulary.pt"
    method = _anyloc(tmp_path, str(path))
    method.use_dataset("corridor")
    assert method.provenance()["vocabulary"]["fitted_on_evaluated_database"] is True


@pytest.mark.parametrize("method", ["anyloc-vlad-dinov2", "dense-vlad"])
def test_a_missing_vocabulary_file_says_what_to_do(tmp_path, method):
    # README: `vprbench describe --method anyloc-vlad-dinov2 --vocabulary c_centers.pt ...`; without the
    # file, the one line names it and what to give instead
    from vprbench import VPRBenchError, create_method

    with pytest.raises(VPRBenchError) as refused:
        create_method(method, vocabulary=str(tmp_path / "c_centers.pt"), cache_dir=tmp_path)
    assert str(tmp_path / "c_centers.pt") in str(refused.value) and "check the path" in str(refused.value)


def test_a_pca_wider_than_the_database_is_refused_before_any_descriptor(shared_data, tmp_path):
    # docs/anyloc.md: pca_dim must be below the number of database images (a clear error); Corridor has 111,
    # known once the dataset is loaded, so no image is described for a run that cannot finish
    from vprbench import VPRBenchError
    from vprbench.evaluation import evaluate
    from vprbench.spec import RunSettings, resolve_spec

    spec = resolve_spec("anyloc", "corridor", options={"backbone": "dinov2_vits14", "weights": "random", "layer": 0,
                                                       "aggregation": "gem", "resize": [28, 28], "pca_dim": 200})
    with pytest.raises(VPRBenchError, match=r"PCA dimension 200 .*111.*pca_dim <= 110"):
        evaluate(spec, RunSettings(data_dir=shared_data, cache_dir=tmp_path))
    assert not list((tmp_path / "stores").rglob("*.h5"))  # nothing was described


def _python_blocks(page: str) -> list[str]:
    from pathlib import Path
    import re

    text = (Path(__file__).resolve().parents[2] / "docs" / page).read_text()
    return re.findall(r"```python\n(.*?)```", text, flags=re.S)


def test_the_python_snippet_of_runs_md_runs_as_written(shared_data, tmp_path):
    # docs/runs.md "From Python": run verbatim but for its two folders, which must still read as the page shows
    (snippet,) = _python_blocks("runs.md")
    assert 'data_dir="../shared/data"' in snippet and '"/tmp/cache"' in snippet
    code = snippet.replace('"../shared/data"', repr(str(shared_data))).replace('"/tmp/cache"', repr(str(tmp_path)))
    scope: dict = {}
    exec(compile(code, "docs/runs.md", "exec"), scope)
    record = scope["record"]
    assert (record["method"], record["dataset"], record["label"]) == ("hog", "corridor", "hog [resize=64x64]")
    assert record["recall"] == {"1": 33.333333, "5": 67.567568}
    # the page's layout: <cache>/results/<protocol hash>/<row key>/<run id>.json, plus the row's method card
    saved = tmp_path / "results" / "f60ac2fa1d51bc67" / record["row_key"] / f"{record['run_id']}.json"
    assert saved.is_file() and saved.with_suffix(".npz").is_file()
    assert (tmp_path / "results" / "methods" / f"{record['row_key']}.json").is_file()


def test_the_stage_snippet_of_stages_md_defines_a_stage(tmp_path):
    # docs/stages.md "Writing a stage": the class skeleton imports and validates its options as the comments say
    (snippet,) = _python_blocks("stages.md")
    scope: dict = {}
    exec(compile(snippet, "docs/stages.md", "exec"), scope)
    options = scope["ConsensusOptions"]()
    assert options.n == 3 and options.k >= 1  # RerankOptions gives k
    assert scope["Consensus"].track == "re-ranked" and scope["Consensus"].Options is scope["ConsensusOptions"]
    import pydantic

    with pytest.raises(pydantic.ValidationError):
        scope["ConsensusOptions"](n=0)


def test_the_budget_row_of_stages_md_gives_the_refusal_it_shows(shared_data, tmp_path, cli):
    # docs/stages.md "Bad input": the row's command, run on Corridor, prints the row's message. It showed the run's
    # one refusal for a command without --rerank-k 111, whose dba is refused after the search instead
    import re
    import shlex
    from pathlib import Path

    text = (Path(__file__).resolve().parents[2] / "docs" / "stages.md").read_text()
    command, message = re.search(r"^\| `(--method hog --rerank dba [^`]*)` on Corridor [^|]*\| `([^`]*)` \|$", text,
                                 flags=re.M).groups()
    code, _, err = cli("evaluate", *shlex.split(command), "--dataset", "corridor", "--data-dir", shared_data,
                       "--cache-dir", tmp_path, "--quiet")
    assert code == 1 and err.strip() == f"error: {message}", err


def test_every_candidates_file_stages_md_reranks_from_is_one_it_exports():
    # docs/stages.md: a reader copying the commands in order has only the files `candidates export --out` wrote
    import re
    from pathlib import Path

    text = (Path(__file__).resolve().parents[2] / "docs" / "stages.md").read_text()
    exported = set(re.findall(r"--out (\S+\.h5)", text))
    used = set(re.findall(r"--candidates (\S+\.h5)", text))
    assert used and used <= exported, used - exported


def test_every_test_the_docs_name_exists():
    # the docs cite tests as evidence ("tests/x.py::test_y"); a moved or renamed test leaves the reader nothing to run
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    missing = []
    for page in [root / "README.md", *sorted((root / "docs").glob("*.md"))]:
        for path, name in re.findall(r"(tests/[\w/.-]+\.py)(?:::(\w+))?", page.read_text()):
            found = root / path
            if not found.is_file() or (name and f"def {name}(" not in found.read_text()):
                missing.append(f"{page.name}: {path}" + (f"::{name}" if name else ""))
    assert not missing, missing


@pytest.mark.parametrize("source, weights, backbone, suggested", [
    ("indoor", "random", "dinov2_vitg14", False),  # docs/anyloc.md: the released centres are refused for these features
    ("structured", None, "dinov2_vits14", False),
    ("structured", None, "dinov2_vitg14", True),  # the release's own setting: its c_centers.pt is taken
])
def test_a_missing_named_vocabulary_suggests_the_released_file_only_where_it_is_taken(tmp_path, source, weights,
                                                                                      backbone, suggested):
    from vprbench import VPRBenchError
    from vprbench.methods.anyloc_lookup import resolve_vocabulary

    name = "dinov2_vitg14@random" if weights == "random" else backbone
    layer = 31 if backbone == "dinov2_vitg14" else 9
    with pytest.raises(VPRBenchError) as refused:
        resolve_vocabulary(source, name, layer, "value", 32, tmp_path)
    message = str(refused.value)
    assert f"vprbench vocabulary fit --domain {source} --method anyloc --backbone {backbone}" in message
    assert ("released c_centers.pt" in message) is suggested, message


def _commands(parser, name="vprbench"):
    import argparse

    yield name, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub, child in action.choices.items():
                yield from _commands(child, f"{name} {sub}")


def test_every_flag_of_every_command_is_documented():
    # a flag `--help` lists but no page names is one a reader cannot find out about (--no-strict, --output, --pca-dim were)
    import re
    from pathlib import Path

    from vprbench.cli.main import build_parser

    root = Path(__file__).resolve().parents[2]
    text = "\n".join(page.read_text() for page in [root / "README.md", *sorted((root / "docs").glob("*.md"))])
    missing = [f"{name}: {action.option_strings}" for name, parser in _commands(build_parser())
               for action in parser._actions if action.option_strings and action.help != "==SUPPRESS=="
               and not {"-h", "--version"} & set(action.option_strings)
               and not any(re.search(re.escape(flag) + r"(?![\w-])", text) for flag in action.option_strings)]
    assert not missing, missing


def test_the_vocabulary_fit_defaults_help_gives_are_the_ones_the_code_and_anyloc_md_use(cli):
    # docs/anyloc.md: a sample of at most 250,000 features by default; initial centres drawn by RandomState(42)
    from pathlib import Path

    from vprbench.aggregation.kmeans import DEFAULT_BUDGET, KMEANS_SEED

    code, out, _ = cli("vocabulary", "fit", "--help")
    out = " ".join(out.split())
    page = (Path(__file__).resolve().parents[2] / "docs" / "anyloc.md").read_text()
    assert code == 0 and f"(default {DEFAULT_BUDGET:,})" in out and f"(default {KMEANS_SEED}, the authors')" in out, out
    assert f"{DEFAULT_BUDGET:,} by" in " ".join(page.split()) and f"RandomState({KMEANS_SEED})" in page


def test_the_export_and_verify_lines_of_contributing_results_md_are_what_they_print(shared_data, tmp_path, cli,
                                                                                    monkeypatch):
    # docs/contributing-results.md "1. Export" and "2. Verify": the commands as shown, on Corridor, print the
    # page's lines (but the run id, the date and the bundle's size); recalls have one decimal, as the leaderboard's
    import re
    import shlex
    from pathlib import Path

    text = (Path(__file__).resolve().parents[2] / "docs" / "contributing-results.md").read_text()
    export, wrote, verify, verified = re.search(r"\$ vprbench (results export [^\n]*)\n(Wrote [^\n]*)\n```.*?"
                                                r"\$ vprbench (results verify [^\n]*)\n([^\n]*)\n", text, flags=re.S).groups()
    monkeypatch.chdir(tmp_path)
    where = ("--data-dir", shared_data, "--cache-dir", tmp_path / "cache")
    assert cli("evaluate", "--method", "hog", "--dataset", "corridor", *where, "--quiet")[0] == 0
    code, out, _ = cli(*shlex.split(export), "--cache-dir", tmp_path / "cache")
    assert code == 0 and out.split(":")[0] == wrote.split(":")[0] and "1 run(s)" in out and "1 run(s)" in wrote
    code, out, _ = cli(*shlex.split(verify.replace("--data-dir /data", "")), *where)
    shown = re.compile(r"\(run \S+, (.*)\Z")
    assert code == 0 and shown.search(out.strip()).group(1) == shown.search(verified).group(1), (out, verified)


def test_the_help_of_datasets_info_says_what_its_cache_dir_is_for(shared_data, tmp_path, cli):
    # `datasets info` uses --cache-dir for a folder of one's own only (and refuses it with a benchmark's name);
    # its --help said "where descriptor stores, vocabularies and results live", as for evaluate
    import re

    code, _, err = cli("datasets", "info", "corridor", "--data-dir", shared_data, "--cache-dir", tmp_path)
    assert code == 1 and "folder of your own" in err
    _, out, _ = cli("datasets", "info", "--help")
    said = " ".join(re.search(r"--cache-dir CACHE_DIR\s+(.*?)\n  --", out, flags=re.S).group(1).split())
    assert "folder of your own" in said and "descriptor stores" not in said, said


def test_registering_a_method_again_is_refused_only_as_add_your_method_md_says(scratch_methods):
    # docs/add-your-method.md: the same factory again (same defaults and description) is no clash; with another
    # description it is refused saying so, not as "a class defined again", which it is not
    import numpy as np

    import vprbench

    class Again(vprbench.Method):
        def describe(self, images):
            return np.full((len(images), 4), 0.5, dtype=np.float32)

    vprbench.register_method("docs-audit-again", Again, defaults={"a": 1}, description="one")
    vprbench.register_method("docs-audit-again", Again, defaults={"a": 1}, description="one")
    with pytest.raises(ValueError, match="same definition but other defaults or description") as refused:
        vprbench.register_method("docs-audit-again", Again, defaults={"a": 2}, description="one")
    assert "a class defined again" not in str(refused.value)

    class Again(vprbench.Method):  # noqa: F811 - a notebook cell run again after an edit
        def describe(self, images):
            return np.full((len(images), 4), 0.5, dtype=np.float32)

    with pytest.raises(ValueError, match="a class defined again"):
        vprbench.register_method("docs-audit-again", Again, defaults={"a": 1}, description="one")


@pytest.mark.parametrize("command", [["run", "plan.toml"], ["reproduce", "anyloc", "--table", "2", "--dry-run"]])
def test_run_and_reproduce_under_torchrun_are_refused_once_by_rank_0(tmp_path, cli, monkeypatch, command):
    # docs/distributed.md: bad input stops every rank with exit code 1 and one `error:` line, said once, by rank 0;
    # `vprbench run` and `reproduce` are refused under torchrun (they were said by every rank)
    monkeypatch.chdir(tmp_path)
    (tmp_path / "plan.toml").write_text('[[methods]]\nname = "hog"\n[[datasets]]\nname = "corridor"\n')
    said = {}
    for rank in (0, 1):
        monkeypatch.setenv("WORLD_SIZE", "2")
        monkeypatch.setenv("RANK", str(rank))
        code, out, err = cli(*command, "--cache-dir", tmp_path)
        assert code == 1 and not out
        said[rank] = err
    assert said[0].startswith("error: ") and said[0].count("error:") == 1 and "runs under torchrun" in said[0]
    assert said[1] == ""


@pytest.mark.parametrize("command", [["evaluate", "--method", "hog", "--dataset", "corridor", "--k", "0"],
                                     ["describe", "--method", "hog", "nope.jpg", "--out", "d.npy"]])
def test_bad_input_met_before_the_ranks_join_is_said_by_the_first_rank_only(tmp_path, cli, monkeypatch, command):
    # docs/distributed.md: bad input is said once; `--k 0` or a missing image, found before the process group is
    # made, was said by every rank (torchrun --nproc-per-node 4: four identical lines)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("WORLD_SIZE", "2")
    said = {}
    for rank in (0, 1):
        monkeypatch.setenv("RANK", str(rank))
        monkeypatch.setenv("LOCAL_RANK", str(rank))
        code, _, err = cli(*command, "--cache-dir", tmp_path)
        assert code == 1
        said[rank] = err
    assert said[0].startswith("error: ") and said[0].count("error:") == 1, said[0]
    assert said[1] == ""
