"""What a researcher reads is right: the command line's own help names every value the methods take."""
import pytest


def _help(capsys, *command) -> str:
    from vprbench.cli.main import main

    with pytest.raises(SystemExit) as stopped:
        main([*command, "--help"])
    assert stopped.value.code == 0
    return " ".join(capsys.readouterr().out.split())


def test_aggregation_help_lists_every_aggregation_anyloc_takes(capsys):
    from vprbench.methods.anyloc import AGGREGATIONS

    shown = _help(capsys, "evaluate").split("--aggregation AGGREGATION ", 1)[1].split(" --clusters", 1)[0]
    assert [name.strip() for name in shown.split(",")] == ["gap", "gmp", "gem", "vlad", "vlad-soft-official", "vlad-soft", "cls"]
    assert set(AGGREGATIONS) == {name.strip() for name in shown.split(",")}


def test_weights_help_names_random(capsys):
    shown = _help(capsys, "evaluate").split("--weights WEIGHTS ", 1)[1].split(" --layer", 1)[0]
    assert "or random" in shown and "pipeline check" in shown
