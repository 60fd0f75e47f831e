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
