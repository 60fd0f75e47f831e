"""A run whose vocabulary bears the name of the authors' release but is not it by sha256 gets a † row of its own:
it was the official row (an imported 'urban' names no datasets, so not even 'fitted on the evaluated database')
and its numbers were set against the paper's."""
from __future__ import annotations

from vprbench.leaderboard.cells import build_board, row_of
from vprbench.methods.anyloc_vocabulary import release


def _with_vocabulary(record, sha256, claimed):
    record["provenance"]["vocabulary"] = {"option": "domain", "name": "urban", "source": "cache", "sha256": sha256,
                                          "authors_release": claimed, "fitted_on_evaluated_database": False}
    return record


def test_a_vocabulary_named_as_the_release_that_is_not_it_gets_its_own_marked_row(make_record):
    theirs = _with_vocabulary(make_record("hog", seed=1), release()["sha256"]["urban"], True)
    own = _with_vocabulary(make_record("hog", seed=2), "0" * 64, False)
    forged = _with_vocabulary(make_record("hog", seed=3), "1" * 64, True)  # a record's word is not its content
    assert row_of(theirs).official
    for record in (own, forged):
        row = row_of(record)
        assert not row.official and not row.like_the_paper
        assert "vocabulary urban not the authors' release" in row.name
    board = build_board([theirs, own])
    assert len(board.rows) == 2 and sum(r.official for r in board.rows) == 1
