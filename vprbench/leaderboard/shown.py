"""What a record's row shows beside its numbers, the same on every table, page and download:
its label, its weights and the marks they earn, the licence of those weights, the machine."""
from __future__ import annotations

from collections.abc import Mapping

from .escape import public, text

#: weights sources that make a row official: the authors' release, or nothing learnt at all
OFFICIAL_WEIGHTS = {"official", "none"}


def row_name(row) -> str:
    """A row's name in a table with a Weights column: its label (escaped), marked † when it is not
    official, with its search and store marks (no Weights column says those): 'hog † hnsw search'."""
    setting = getattr(row, "setting", "")
    return f"{text(row.label)}{' †' if not row.official else ''}{f' {text(setting)}' if setting else ''}"


def weight_marks(row) -> str:
    """The row's marks about what it learnt (weights, stages' weights, fitted on the evaluated
    database), without those of its search and store."""
    setting = set(filter(None, getattr(row, "setting", "").split("; ")))
    return "; ".join(m for m in row.mark.split("; ") if m and m not in setting)


def method_label(record: dict) -> str:
    """The method name, with the options the user set on top of its preset: ablations get rows of their own."""
    from ..spec import RunSpec

    return RunSpec.model_validate(record["spec"]).label()


def weights_of(record: dict) -> tuple[str, str]:
    """(key, mark): key 'official' for official weights, else one key per weights source;
    mark is the label shown beside a non-official row ('' for official)."""
    weights = (record.get("provenance") or {}).get("weights") or {}
    source = weights.get("source", "undeclared")
    if source in OFFICIAL_WEIGHTS:
        return "official", ""
    if source == "user":
        digest = str(weights.get("sha256", ""))[:12]
        return f"user:{digest}", f"user weights sha256:{digest}"
    return source, f"weights {source}"


#: the mark of a run with a part fitted on the database it is evaluated on (the field's "transductive")
TRANSDUCTIVE = "fitted on the evaluated database"


def vocabulary_mark(record: dict) -> str:
    """The mark of a run whose vocabulary bears the name of the authors' released centres (at their setting)
    but is not them by sha256 (fitted or imported under that name): never the paper's setting, nor its row."""
    vocabulary = (record.get("provenance") or {}).get("vocabulary") or {}
    if not isinstance(vocabulary, Mapping) or "authors_release" not in vocabulary:
        return ""
    from ..methods.anyloc_vocabulary import release

    # by the sha256 the record gives, not its word (a contributed record may claim the release)
    if vocabulary.get("sha256") in release()["sha256"].values():
        return ""
    from ..text import shortened

    return f"vocabulary {shortened(str(vocabulary.get('name')), 60)} not the authors' release"


def weights_shown(row, record: dict) -> str:
    """The Weights column, the same on every table, page and download: the row's marks of what it
    learnt (weight_marks), else
    'official', 'none (nothing learnt)' for a method with nothing learnt, or what it learnt
    (e.g. 'vocabulary fitted on 2 images in ...') when its only learnt parts were fitted elsewhere."""
    if weight_marks(row):  # an HNSW search or a float16 store is not what the weights are
        return weight_marks(row)
    provenance = record.get("provenance") or {}
    learnt = [part for part in provenance.get("learnt") or [] if isinstance(provenance.get(part), dict)]
    if learnt:
        return public("; ".join(f"{part} fitted on {provenance[part].get('fitted_on') or 'data it does not name'}"
                                for part in learnt))
    return "none (nothing learnt)" if (provenance.get("weights") or {}).get("source") == "none" else "official"


def licence_shown(record: dict) -> str:
    """The Licence column, beside the row everywhere: the licence of the weights the run used, as
    its record declares it (AnyLoc: the backbone's manifest entry), '(gated)' when access to them
    must be requested; '–' when the record declares none or the weights were random."""
    provenance = record.get("provenance") or {}
    if (provenance.get("weights") or {}).get("source") == "random":
        return "–"
    card = next((c for c in (provenance.get("backbone"), provenance.get("weights")) if isinstance(c, dict)
                 and c.get("licence")), None)
    if card is None:
        return "–"
    return f"{card['licence']} (gated)" if card.get("gated") is True else str(card["licence"])


def descriptor_bytes(record: dict) -> int | None:
    """Bytes of one descriptor as stored: the record's, else its dimensions times its store's
    width (a float16 store holds 2 bytes per dimension, not 4)."""
    if record.get("descriptor_bytes"):
        return int(record["descriptor_bytes"])
    dim = record.get("descriptor_dim")
    width = 2 if (record.get("spec") or {}).get("store_dtype") == "float16" else 4
    return int(dim) * width if isinstance(dim, (int, float)) and dim else None


def hardware_of(record: dict) -> str:
    """The machine a run was on, as its record names it."""
    found = record.get("hardware") or {}
    if not isinstance(found, dict) or not found:
        return "unknown"
    if "cpu" not in found and "cpu_count" not in found:
        return str(found.get("note") or "unknown")
    gpu = found.get("cuda")
    return (f"{found.get('cpu') or found.get('machine') or 'unknown CPU'} ({found.get('cpu_count', '?')} cores), "
            f"{gpu if gpu else 'no GPU'}")


#: why a run on random weights fills no cell
RANDOM = ("random weights (a pipeline check, e.g. without access to gated weights): numbers from random "
          "initialisation never fill a cell")


#: what every terminal surface says of such a run beside (or instead of) its numbers
PIPELINE_CHECK = "random weights: a pipeline check, not a result"


def random_weights(record: dict) -> bool:
    """The method or any stage ran on random weights (as recorded, or as its options asked)."""
    weights = (record.get("provenance") or {}).get("weights") or {}
    spec = record.get("spec") or {}
    stage_options = [s.get("options") for s in spec.get("stages") or [] if isinstance(s, dict)]
    return (weights.get("source") == "random" or asks_random(spec.get("options"))
            or any(w.get("source") == "random" for _, w in _stage_weights(record))
            or any(asks_random(options) for options in stage_options))


def asks_random(options) -> bool:
    """Whether a method's or a stage's options ask for random weights (`weights=random`)."""
    return isinstance(options, Mapping) and options.get("weights") == "random"


def _stage_weights(record: dict) -> list[tuple[str, dict]]:
    """(name, weights provenance) of each stage of the run that has weights (`Stage.provenance`)."""
    found = []
    for stage in record.get("stages") or []:
        weights = (stage.get("provenance") or {}).get("weights") if isinstance(stage, dict) else None
        if isinstance(weights, dict):
            found.append((str(stage.get("name", "stage")), weights))
    return found


def stage_marks(record: dict) -> list[str]:
    """A stage whose weights are not its authors' release marks the row, as a method's do:
    'superpoint-lightglue user weights sha256:1a2b3c4d5e6f'."""
    marks = []
    for name, weights in _stage_weights(record):
        source = weights.get("source", "undeclared")
        if source in OFFICIAL_WEIGHTS:
            continue
        parts = [w for w in (weights.get("files") or {}).values() if isinstance(w, dict)] or [weights]
        digests = [f"sha256:{str(w['sha256'])[:12]}" for w in parts if w.get("source") == source and w.get("sha256")]
        marks.append(" ".join([name, f"{source} weights", ", ".join(digests)]).strip())
    return marks


def left_out(record: dict) -> tuple[str, str, str]:
    """(run id, row label, dataset) of a run left out of every cell, as the terminal and the site
    name it; the label falls back to the method (a damaged record may lack one), paths cut."""
    label = record.get("label") or record.get("method")
    return tuple(public(value) if value else "?" for value in (record.get("run_id"), label, record.get("dataset")))


def plugins_shown(record: dict) -> str:
    """The run's method and stages that vprbench itself does not provide, each with the distribution and
    version it came from (the record's `origins`), escaped; '–' when there are none or the record predates them."""
    found = record.get("origins") if isinstance(record.get("origins"), dict) else {}
    parts = [found.get("method"), *(found.get("stages") if isinstance(found.get("stages"), list) else [])]
    shown = []
    for part in parts:
        if not isinstance(part, dict) or part.get("module") in (None, "vprbench"):
            continue
        where = (f"{part['distribution']} {part.get('version') or ''}".strip() if part.get("distribution")
                 else f"{part['module']} (no installed distribution)")
        shown.append(text(f"{part.get('name') or '?'}: {where}"))
    return "; ".join(shown) or "–"
