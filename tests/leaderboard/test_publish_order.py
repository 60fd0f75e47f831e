"""Two publishes to one folder at once: the site is the one built from the results read last, whichever
publish ends last. One that read them earlier and ends later (more datasets to draw, a slower machine) used to
swap its older site over the newer one: a run stored between the two reads vanished from the site, though the
publish that showed it had said so and ended first."""
import json
import os
import subprocess
import sys
import warnings

from vprbench.evaluation import save_result
from vprbench.leaderboard import site


def published_runs(docs):
    return sorted(entry["run_id"] for entry in json.loads((docs / "leaderboard" / "downloads" / "leaderboard.json")
                                                          .read_text()))


def test_a_publish_that_read_the_results_first_and_ends_last_keeps_the_newer_site(tmp_path, make_record, monkeypatch):
    docs = tmp_path / "docs"
    first = make_record("hog", seed=1, created="2026-01-01T00:00:00+00:00")
    save_result(first)
    later = make_record("hog", "17places", seed=2, created="2026-01-02T00:00:00+00:00")
    write_section, calls = site.write_section, []

    def interleaved(out, board, records, **kwargs):
        calls.append(sorted(r["run_id"] for r in records))
        if len(calls) == 1:  # the first publish has read the results: a run is stored, a second publish runs whole
            save_result(later)
            second = subprocess.run([sys.executable, "-m", "vprbench", "leaderboard", "publish", "--to", str(docs)],
                                    env=dict(os.environ), capture_output=True, text=True, timeout=300)
            assert second.returncode == 0 and "Traceback" not in second.stderr, second.stderr
            assert published_runs(docs) == sorted([first["run_id"], later["run_id"]])
        return write_section(out, board, records, **kwargs)

    monkeypatch.setattr(site, "write_section", interleaved)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert site.publish(docs) == docs / "leaderboard"
    assert calls == [[first["run_id"]]]
    assert published_runs(docs) == sorted([first["run_id"], later["run_id"]])
    assert any("read the results after this one" in str(w.message) for w in caught)
    assert sorted(p.name for p in docs.iterdir() if p.name.startswith(".leaderboard-")) == []  # no staging left
    # alone again, a publish replaces the site as before
    save_result(make_record("hog", "gardens-point", seed=3, created="2026-01-03T00:00:00+00:00"))
    monkeypatch.setattr(site, "write_section", write_section)
    site.publish(docs)
    assert len(published_runs(docs)) == 3
