"""What a contributed record says beside its numbers, checked against what decides it.

Re-scoring proves a record's metrics; the names around them choose where the numbers land and
what they are called: the method and label name the row, the dataset, protocol and domain the
column and the table (structured or not), the weights (a stage's too) whether the row is official,
the stages the track (single-image, re-ranked or sequence: a table of its own). Each must be
what the record's own spec says, or what vprbench ships for its protocol hash; a record that
says otherwise claims a run it did not make, and is refused. So is a second record under a run id,
and a method card (methods/<row key>.json) that describes another method than its records.
"""
from __future__ import annotations

from ..spec import RunSpec
from ..text import shortened
from .export import CARDS, card_disagreement


def malformed(record: dict) -> list[str]:
    """One line per part of the record that the board reads as a table (what the weights and stages learnt)
    but is not one: the row's name and marks are read from them."""
    found = []

    def table(value, where: str, keys=()) -> None:
        if value is None:
            return
        if not isinstance(value, dict):
            found.append(f"its {where} is a JSON {type(value).__name__}, not a table; a record vprbench writes has one")
            return
        for key in keys:
            table(value.get(key), f"{where}.{key}")
        if where.endswith("weights") and not isinstance(value.get("source", ""), str):
            found.append(f"its {where}.source is a JSON {type(value['source']).__name__}, not a name")

    table(record.get("provenance"), "provenance", ("weights", "vocabulary"))
    for at, stage in enumerate(record.get("stages") or []):
        table(stage.get("provenance") if isinstance(stage, dict) else None, f"stages[{at}].provenance", ("weights",))
    return found


def false_claims(record: dict) -> list[str]:
    """One line per name the record gives that its spec or vprbench's manifests contradict."""
    from ..datasets import dataset_manifests
    from ..evaluation.identity import benchmark_protocols
    from ..stages.registry import available_stages
    from ..weights import is_file_identity, weights_provenance

    spec = RunSpec.model_validate(record["spec"])
    # a stage's label leaves out its defaults, known only where its plugin is installed
    missing = [stage.name for stage in spec.stages if stage.name not in available_stages()]
    protocol = record["protocol"]
    given = [("method", record["method"], spec.method, "its spec"),
             ("label", record.get("label", spec.label()), spec.label(), "its spec"),
             ("dataset", record["dataset"], spec.dataset.name, "its spec"),
             ("dataset kind", record["dataset_kind"], spec.dataset.kind, "its spec"),
             ("protocol id", protocol["id"], spec.dataset.protocol_id, "its spec"),
             ("protocol name", protocol.get("name"), spec.dataset.protocol, "its spec")]
    shipped = benchmark_protocols(record["dataset"]).get(protocol["hash"])
    if shipped is not None:  # else no benchmark protocol: the ground truth step names it
        as_shipped = f"protocol {protocol['hash']} as vprbench ships it"
        given += [("protocol id", protocol["id"], shipped["id"], as_shipped),
                  ("protocol name", protocol.get("name"), shipped["name"], as_shipped),
                  ("domain", record.get("domain"), dataset_manifests()[record["dataset"]].domain,
                   f"the {record['dataset']} manifest")]
    weights = spec.files.get("weights")
    if is_file_identity(weights):  # a weights file, known by its content (a malformed one is no file's)
        stated = ((record.get("provenance") or {}).get("weights") or {}).get("source")
        given.append(("weights source", stated, weights_provenance(weights)["source"],
                      f"its weights file {weights[:19]}"))
    given += _stage_weights_claims(record, spec, is_file_identity, weights_provenance)
    track, tracks = record.get("track") or "single-image", _tracks(spec, available_stages())
    if track not in tracks:  # the table its numbers land in: a re-ranked run among single-image ones, say
        given.append(("track", track, " or ".join(tracks), "its spec (its stages)"))
    # what a record claims is any JSON a stranger wrote: cut, so one claim is one readable line
    problems = [f"it says {what} {shortened(repr(claimed))}, but {source} says {shortened(repr(truth))}; a record "
                "names only the run it made"
                for what, claimed, truth, source in given if claimed != truth and not (what == "label" and missing)]
    if missing and record.get("label", spec.label()) != spec.label():
        problems.append(f"its stage {', '.join(missing)} is not installed here, so its label cannot be checked: install "
                        "the package that provides it ('vprbench stages list' shows what is installed), then verify again")
    return problems


def _tracks(spec: RunSpec, installed: dict) -> tuple[str, ...]:
    """The table a run's numbers may belong in (stages/run.track_of): single-image without a stage, sequence
    with a sequence stage, else re-ranked; either of the two when a stage is not installed here."""
    if not spec.stages:
        return ("single-image",)
    if any(stage.name not in installed for stage in spec.stages):
        return ("re-ranked", "sequence")
    return ("sequence",) if any(installed[s.name].cls.track == "sequence" for s in spec.stages) else ("re-ranked",)


def _stage_weights_claims(record: dict, spec: RunSpec, is_file_identity, weights_provenance) -> list[tuple]:
    """(what, claimed, truth, source) for each stage whose spec names its weights files by sha256: the
    source its record gives (the row's mark: none for 'official') must be what those files are, 'user'
    when any is no authors' release, as the stage itself says it."""
    found, costs = [], record.get("stages") if isinstance(record.get("stages"), list) else []
    for at, stage in enumerate(spec.stages):
        named = stage.files.get("weights")
        files = list(named.values()) if isinstance(named, dict) else [named]
        if not files or not all(is_file_identity(f) for f in files):  # none, random, or a folder: not known by sha256
            continue
        sources = {weights_provenance(f)["source"] for f in files}
        cost = costs[at] if at < len(costs) and isinstance(costs[at], dict) else {}
        # its provenance and weights are tables or absent: `malformed` refused the record before any claim is read
        stated = ((cost.get("provenance") or {}).get("weights") or {}).get("source")
        found.append((f"stage {stage.name} weights source", stated, "user" if "user" in sources else "official",
                      f"its weights file{'s' if len(files) > 1 else ''} {', '.join(f[:19] for f in files)}"))
    return found


def one_record_per_run(verdicts: list) -> None:
    """A run id names one run (pages and `results export --run` find it by its id alone): a second
    record under it, in another row or protocol folder, is refused."""
    first: dict[str, str] = {}
    for verdict in verdicts:
        if verdict.run_id in first:
            verdict.problems.append(f"its run id is also that of {first[verdict.run_id]}; a run id names one run")
        first.setdefault(verdict.run_id, verdict.member)


def false_card(data: bytes, record: dict) -> list[str]:
    """The row's method card (stored beside the runs, once per row) describes the record's method:
    each field the record decides that the card has must be the record's."""
    why = card_disagreement(data, record)
    return [f"its method card {CARDS}/{record['row_key']}.json {why}"] if why else []
