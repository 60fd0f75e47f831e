"""Getting data: download, import, verify, and the errors each gives on bad input."""
from __future__ import annotations

import json
import re

import numpy as np
import pytest

import vprbench.datasets as datasets
from vprbench.cli.main import build_parser, main
from vprbench.datasets import import_dataset, load_dataset, read_registry, verify_dataset
from vprbench.errors import VPRBenchError


@pytest.fixture
def gardens(tmp_path, make_images, save_rows):
    """A complete Gardens Point copy in the release layout, outside the data root."""
    root = tmp_path / "elsewhere" / "gardens"
    names = [f"Image{i:03d}.jpg" for i in range(200)]
    make_images(root / "day_right", names)
    make_images(root / "night_right", names)
    save_rows(root / "gardens_gt.npy", [range(max(0, i - 2), min(200, i + 3)) for i in range(200)])
    return root


def run(*argv) -> int:
    args = build_parser().parse_args(list(argv))
    return args.run(args)


def test_wrong_layout_names_what_each_layout_expects(tmp_path):
    (tmp_path / "gardens" / "day_right").mkdir(parents=True)
    with pytest.raises(VPRBenchError) as error:
        load_dataset("gardens-point", tmp_path)
    message = str(error.value)
    assert "layout 'folders' (the authors' release) is missing folder 'night_right', file 'gardens_gt.npy'" in message
    assert "layout 'vpr-bench' is missing folder 'ref', folder 'query', file 'ground_truth_new.npy'" in message


def test_missing_dataset_says_how_to_get_it(tmp_path):
    with pytest.raises(VPRBenchError, match=r"not in the data root .*looked for .*hawkins_long_corridor.*hawkins_long_corridor.tar.gz.*datasets import hawkins"):
        load_dataset("hawkins", tmp_path)


def test_count_differing_from_manifest_warns_and_fails_when_strict(tmp_path, gardens):
    (gardens / "night_right" / "Image199.jpg").unlink()
    (gardens / "night_right" / "Image198.jpg").unlink()
    with pytest.raises(VPRBenchError, match="has 200 query rows .* but 198 query images"):
        load_dataset("gardens-point", gardens.parent)
    # with matching ground truth, only the count differs from the manifest
    np.save(gardens / "gardens_gt.npy", np.load(gardens / "gardens_gt.npy", allow_pickle=True)[:198], allow_pickle=True)
    with pytest.warns(UserWarning, match="198 query images .* the manifest expects 200"):
        load_dataset("gardens-point", gardens.parent)
    with pytest.raises(VPRBenchError, match="expects 200.*--strict"):
        load_dataset("gardens-point", gardens.parent, strict=True)
    report = verify_dataset("gardens-point", gardens.parent)
    assert report.ok and report.warnings[0] == "198 query images, the manifest expects 200 (+2)"
    strict = verify_dataset("gardens-point", gardens.parent, strict=True)
    assert not strict.ok and strict.problems == ["198 query images, the manifest expects 200 (+2)"]


def test_unreadable_ground_truth_is_a_clear_error(gardens):
    (gardens / "gardens_gt.npy").write_bytes(b"not a numpy file")
    with pytest.raises(VPRBenchError, match=r"Cannot read ground truth .*gardens_gt.npy.*re-download"):
        load_dataset("gardens-point", gardens.parent)
    report = verify_dataset("gardens-point", gardens.parent)
    assert not report.ok and "gardens_gt.npy" in report.problems[0]


def test_ground_truth_pointing_past_the_database(gardens, save_rows):
    save_rows(gardens / "gardens_gt.npy", [[250]] * 200)
    with pytest.raises(VPRBenchError, match=r"names database image 250, outside 0..199"):
        load_dataset("gardens-point", gardens.parent).positives


def test_verify_reports_missing_paths_and_corrupt_images(gardens, tmp_path):
    report = verify_dataset("gardens-point", tmp_path)
    assert not report.ok and report.problems[0].startswith(f"folder {tmp_path / 'gardens'} does not exist")

    (gardens / "day_right" / "Image000.jpg").unlink()
    (gardens / "day_right" / "Image000.jpg").write_bytes(b"broken jpeg")
    report = verify_dataset("gardens-point", gardens.parent, sample=3)
    assert report.images_checked == 6
    assert report.problems == [report.problems[0]] and "Cannot read image" in report.problems[0]
    assert "Image000.jpg" in report.problems[0]

    with pytest.raises(VPRBenchError, match="--sample must be 0 or more"):
        verify_dataset("gardens-point", gardens.parent, sample=-1)
    assert verify_dataset("gardens-point", gardens.parent, sample=0).images_checked == 0

    (gardens / "gardens_gt.npy").unlink()
    report = verify_dataset("gardens-point", gardens.parent)
    assert report.problems == [
        "layout 'folders' (day_right/, night_right/, gardens_gt.npy) is missing: gardens_gt.npy",
        "layout 'vpr-bench' (ref/, query/, ground_truth_new.npy) is missing: ref/, query/, ground_truth_new.npy",
    ]


def test_verify_netvlad_mat_with_missing_images(tmp_path, make_images):
    from scipy.io import savemat

    root = tmp_path / "Oxford_Robotcar"
    make_images(root / "oxDataPart", ["a.png"])
    struct = np.empty((1, 8), dtype=object)
    for k, value in enumerate((np.array(["a.png", "b.png"]), np.zeros((2, 2)), np.array(["c.png"]), np.zeros((1, 2)), 2, 1, 25, 625)):
        struct[0, k] = value
    savemat(root / "oxdatapart.mat", {"dbStruct": struct})
    with pytest.raises(VPRBenchError, match=r"2 image\(s\) named in oxdatapart.mat are missing .* e.g. 'b.png'"):
        load_dataset("oxford", tmp_path)


def test_import_validates_before_registering(tmp_path, gardens, monkeypatch):
    data_root = tmp_path / "data"
    broken = tmp_path / "broken"
    (broken / "day_right").mkdir(parents=True)
    with pytest.raises(VPRBenchError, match="missing folder 'night_right'"):
        import_dataset("gardens-point", broken, data_root)
    assert not (data_root / "datasets.json").exists()  # nothing half-imported

    dataset = import_dataset("gardens-point", gardens, data_root)
    assert (len(dataset.database), len(dataset.queries)) == (200, 200)
    assert read_registry(data_root) == {"gardens-point": str(gardens.resolve())}
    assert load_dataset("gardens-point", data_root).root == gardens.resolve()
    assert datasets.is_on_disk("gardens-point", data_root) and not datasets.is_on_disk("hawkins", data_root)
    # a later failed import of another dataset leaves the registry as it was
    with pytest.raises(VPRBenchError):
        import_dataset("hawkins", broken, data_root)
    assert read_registry(data_root) == {"gardens-point": str(gardens.resolve())}


def test_import_strict_refuses_wrong_counts(tmp_path, gardens, save_rows):
    (gardens / "day_right" / "Image199.jpg").unlink()
    save_rows(gardens / "gardens_gt.npy", [range(max(0, i - 2), min(199, i + 3)) for i in range(200)])
    with pytest.raises(VPRBenchError, match="199 database images .* expects 200"):
        import_dataset("gardens-point", gardens, tmp_path / "data", strict=True)
    assert read_registry(tmp_path / "data") == {}


def test_damaged_registry_is_a_clear_error(tmp_path):
    (tmp_path / "datasets.json").write_text("{not json")
    with pytest.raises(VPRBenchError, match="Cannot read the dataset registry .*datasets.json"):
        load_dataset("hawkins", tmp_path)


def test_download_without_direct_source_prints_instructions(tmp_path):
    with pytest.raises(VPRBenchError, match=r"no direct download\. Download baidu_datasets.tar.gz from the AnyLoc public release"):
        datasets.download_dataset("baidu-mall", tmp_path)


def test_download_with_direct_source_checks_counts(tmp_path, monkeypatch, shared_data):
    """The pooch download is replaced by a local copy (tests never touch the network)."""
    import shutil

    calls = []

    def fake_download(manifest, root, progress=True, data_dir=None):
        calls.append(manifest.name)
        shutil.copytree(shared_data / "corridor", root)
        return root

    monkeypatch.setattr(datasets, "download", fake_download)
    dataset = datasets.download_dataset("corridor", tmp_path)
    assert calls == ["corridor"] and (len(dataset.database), len(dataset.queries)) == (111, 111)
    datasets.download_dataset("corridor", tmp_path)  # already there: not fetched again
    assert calls == ["corridor"]


def test_cli_import_verify_list_info(tmp_path, gardens, capsys):
    data = ["--data-dir", str(tmp_path / "data")]
    assert run("datasets", "import", "gardens-point", str(gardens), *data) == 0
    assert "Imported 'gardens-point'" in capsys.readouterr().out
    assert run("datasets", "verify", "gardens-point", "--json", *data) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["ok"] and report["layout"] == "folders"
    assert report["summary"]["positive_pairs"] == 200 * 5 - 6
    assert run("datasets", "verify", "hawkins", *data) == 1
    out = capsys.readouterr().out
    assert out.startswith("hawkins: PROBLEMS") and "does not exist" in out
    assert main(["datasets", "download", "hawkins", *data]) == 1
    assert "no direct download" in capsys.readouterr().err
    # list and info see the imported copy
    assert run("datasets", "list", "--json", *data) == 0
    rows = {r["name"]: r for r in json.loads(capsys.readouterr().out)}
    assert rows["gardens-point"]["on_disk"] and not rows["hawkins"]["on_disk"]
    assert (rows["gardens-point"]["radius"], rows["gardens-point"]["radius_unit"]) == (2, "frames")
    assert run("datasets", "info", "gardens-point", "--json", *data) == 0
    info = json.loads(capsys.readouterr().out)
    assert (info["database"], info["queries"], info["queries_with_positives"], info["positive_pairs"]) == (200, 200, 200, 994)
    assert (info["unit"], info["radius"], info["radius_unit"], info["domain"]) == ("positives", 2, "frames", "indoor")
    assert info["layout"] == "folders" and "night_right" in info["notes"]


def test_the_list_shows_every_name_whole_in_a_narrow_terminal(tmp_path, capsys, monkeypatch):
    """Was: at 80 columns the table cut a name to 'mid-atlantic-…', not a name one can type."""
    monkeypatch.setenv("COLUMNS", "80")
    assert main(["datasets", "list", "--data-dir", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "…" not in out
    shown = {line.split("│")[1].strip() for line in out.splitlines() if line.startswith("│")}
    assert set(datasets.dataset_manifests()) <= shown


def test_importing_from_a_path_that_is_no_folder_says_what_to_give(tmp_path, capsys):
    """Was: "/data/pitts30k is not a folder." for the README's example path: neither that it is missing
    nor what to give instead."""
    data = ["--data-dir", str(tmp_path / "data")]
    (tmp_path / "copies").mkdir()
    assert main(["datasets", "import", "pitts30k", str(tmp_path / "copies" / "pitts30k"), *data]) == 1
    assert capsys.readouterr().err == (f"error: Cannot import 'pitts30k': {tmp_path / 'copies' / 'pitts30k'} does not "
                                       f"exist; closest existing path: {tmp_path / 'copies'}. Give the folder holding "
                                       "your copy of pitts30k.\n")
    (tmp_path / "copy.tar.gz").write_bytes(b"")
    assert main(["datasets", "import", "pitts30k", str(tmp_path / "copy.tar.gz"), *data]) == 1
    assert "copy.tar.gz is a file, not a folder. Give the folder holding your copy of pitts30k." in capsys.readouterr().err
    assert not (tmp_path / "data").exists()


def test_a_database_image_more_or_fewer_is_refused_where_positives_are_indices(tmp_path, gardens):
    """Was a warning: a copy with one database image more (or fewer) was read, its ground truth (indices into
    the sorted database) then pointing every later index at another image: a wrong Recall, exit 0."""
    import shutil

    shutil.copy(gardens / "day_right" / "Image010.jpg", gardens / "day_right" / "Image010a.jpg")
    said = "201 database images at .* the manifest expects 200. Its ground truth names database images by their position"
    with pytest.raises(VPRBenchError, match=said) as error:
        load_dataset("gardens-point", gardens.parent)
    # the check it suggests names the data root given (was: none, the default one's copy checked)
    assert str(error.value).endswith(f"('vprbench datasets verify gardens-point --data-dir {gardens.parent}' lists "
                                     "what differs).")
    with pytest.raises(VPRBenchError, match=said) as error:
        import_dataset("gardens-point", gardens, tmp_path / "data")
    assert "datasets verify" not in str(error.value)  # it would check the data root's copy, not this folder
    assert not (tmp_path / "data" / "datasets.json").exists()
    report = verify_dataset("gardens-point", gardens.parent)
    assert not report.ok and report.problems[0].startswith("201 database images, the manifest expects 200 (-1). Its")
    (gardens / "day_right" / "Image010a.jpg").unlink()
    (gardens / "day_right" / "Image199.jpg").unlink()  # one fewer: named as such, not as an index past the end
    with pytest.raises(VPRBenchError, match="199 database images at .* expects 200. Its ground truth"):
        import_dataset("gardens-point", gardens, tmp_path / "data")


def test_import_and_verify_name_an_empty_image(tmp_path, gardens):
    """Was: a zero-byte image (a download that stopped) was imported; verify's sample or the run named it later."""
    (gardens / "night_right" / "Image005.jpg").unlink()  # a hard link to every other image: not truncated
    (gardens / "night_right" / "Image005.jpg").write_bytes(b"")
    with pytest.raises(VPRBenchError, match=r"^Cannot import 'gardens-point': 1 listed image\(s\) are empty or no file, "
                                            r"e\.g\. .*Image005\.jpg; get those images again"):
        import_dataset("gardens-point", gardens, tmp_path / "data")
    assert not (tmp_path / "data" / "datasets.json").exists()
    problems = verify_dataset("gardens-point", gardens.parent, sample=1).problems  # whatever its sample decodes
    assert problems[0].startswith("1 listed image(s) are empty or no file, e.g. ") and "Image005.jpg" in problems[0]


@pytest.mark.parametrize("bad, shown", [(1.7, "1.7"), (float("nan"), "nan"), (2**70, str(2**70))])
def test_positive_lists_refuse_indices_that_are_not_whole_numbers(gardens, save_rows, bad, shown):
    # a cast would make 1.7 read as image 1 and NaN a huge negative; 2**70 overflowed with a traceback
    lists = [[i] for i in range(200)]
    lists[5] = [bad]
    save_rows(gardens / "gardens_gt.npy", lists)
    with pytest.raises(VPRBenchError, match=rf"gardens_gt.npy: {shown} is not an image index"):
        load_dataset("gardens-point", gardens.parent).positives


@pytest.mark.parametrize("query, said", [
    (5.5, "5.5 is not an image index"), ("5", "'5' is not an image index"),
    # a list there was read as its first number: row [5, 9] became query 5's, 9 dropped in silence
    ([5, 9], "[5, 9] is not a query index (one whole number)"), ([5], "[5] is not a query index"),
    ([], "[] is not a query index")])
def test_vpr_bench_rows_refuse_a_query_cell_that_is_not_one_whole_number(tmp_path, make_images, query, said):
    root = tmp_path / "corridor"
    make_images(root / "ref", [f"{i:07d}.jpg" for i in range(111)])
    make_images(root / "query", [f"{i:07d}.jpg" for i in range(111)])
    rows = np.empty((111, 2), dtype=object)
    for i in range(111):
        rows[i, 0], rows[i, 1] = (query if i == 5 else i), [i]
    np.save(root / "ground_truth_new.npy", rows, allow_pickle=True)
    with pytest.raises(VPRBenchError, match=re.escape(said)):
        load_dataset("corridor", tmp_path)


def test_dropping_frames_past_the_references_keeps_negative_indices_an_error(tmp_path, make_images, save_rows):
    # 17 Places' lists name frames 406, 407 (dropped, as AnyLoc does); a -1 is a damaged file, not such a frame
    root = tmp_path / "17places"
    make_images(root / "ref", [f"{i:07d}.jpg" for i in range(406)])
    make_images(root / "query", [f"{i:07d}.jpg" for i in range(406)])
    lists = [[i, i + 2] for i in range(406)]
    save_rows(root / "ground_truth_new.npy", lists)
    lists[3] = [-1]  # VPR-Bench's mark of a query without a true match (as in GardensPoint_TN)
    save_rows(root / "ground_truth_new.npy", lists)
    dataset = load_dataset("17places", tmp_path)
    assert (dataset.positives[405].tolist(), dataset.positives[3].tolist()) == ([405], [])
    lists[7] = [-1, 7]
    save_rows(root / "ground_truth_new.npy", lists)
    with pytest.raises(VPRBenchError, match=r"query 7 names database image -1, outside 0..405"):
        load_dataset("17places", tmp_path).positives


@pytest.mark.parametrize("bad, shown", [(1.7, "1.7"), (10**30, str(10**30))])
def test_top_k_csv_refuses_indices_that_are_not_whole_numbers(tmp_path, make_images, bad, shown):
    root = tmp_path / "test_40_midref_rot0"
    make_images(root / "reference_images", [f"{i:04d}.png" for i in range(102)])
    make_images(root / "query_images", [f"{i:04d}.png" for i in range(71)])
    header = ",".join(f"top_{k}_ref_ind" for k in range(1, 6))
    rows = [",".join([str(bad) if q == 5 and k == 0 else str(q) for k in range(5)]) for q in range(71)]
    (root / "gt_matches.csv").write_text(header + "\n" + "\n".join(rows) + "\n")
    with pytest.raises(VPRBenchError, match=rf"gt_matches.csv: .*{shown}"):
        load_dataset("nardo-air", tmp_path).positives


def test_a_moved_import_says_to_import_again_into_the_same_data_root(tmp_path, gardens):
    # it said "Import it again with 'vprbench datasets import gardens-point PATH'": run as printed, that
    # registers the copy in the default data root, and the run naming this one still fails
    data_root = tmp_path / "data"
    import_dataset("gardens-point", gardens, data_root)
    gardens.rename(tmp_path / "moved")
    with pytest.raises(VPRBenchError) as refused:
        load_dataset("gardens-point", data_root)
    command = re.search(r"'(vprbench datasets import [^']*)'", str(refused.value)).group(1)
    args = build_parser().parse_args(command.split()[1:])
    assert args.name == "gardens-point" and args.data_dir == str(data_root.resolve())


def test_the_import_hint_for_a_dataset_not_there_names_its_data_root(tmp_path):
    # it said "or run 'vprbench datasets import hawkins PATH'": that registers the copy in the default
    # data root, and the run naming this one still finds nothing
    with pytest.raises(VPRBenchError) as refused:
        load_dataset("hawkins", tmp_path)
    command = re.search(r"'(vprbench datasets import [^']*)'", str(refused.value)).group(1)
    args = build_parser().parse_args(command.split()[1:])
    assert args.name == "hawkins" and args.data_dir == str(tmp_path)


def test_hints_name_the_data_root_the_user_gave(tmp_path, gardens, make_images, monkeypatch, capsys):
    """Was: the commands a hint suggested named the parent of the folder read (an imported copy's, or the
    folder being imported's) as --data-dir, or no --data-dir at all: followed, they ran on another root."""
    import shutil

    from vprbench.datasets.layouts.base import EXPECTS

    data = tmp_path / "data"
    assert run("datasets", "import", "gardens-point", str(gardens), "--data-dir", str(data)) == 0
    moved = shutil.move(gardens, tmp_path / "moved")
    assert run("datasets", "verify", "gardens-point", "--data-dir", str(data)) == 1
    out = capsys.readouterr().out
    assert f"'vprbench datasets import gardens-point PATH --data-dir {data}' on a copy elsewhere" in out, out
    # a folder being imported that is in no layout: where a download goes in the data root named
    with pytest.raises(VPRBenchError) as error:
        import_dataset("corridor", tmp_path / "elsewhere", data)
    assert f"Run 'vprbench datasets download corridor --data-dir {data}' to fetch it into {data / 'corridor'}." \
        in str(error.value)
    # a part missing that only the reader looks for: the check it suggests is of this data root's copy
    shutil.move(moved, gardens)
    (gardens / "gardens_gt.npy").unlink()
    monkeypatch.setitem(EXPECTS, "folders", lambda options: [])
    said = f"expected file 'gardens_gt.npy' under {gardens.resolve()} (layout 'folders') but it is missing."
    with pytest.raises(VPRBenchError) as error:
        load_dataset("gardens-point", data)
    assert str(error.value).endswith(f"{said} The copy is incomplete: 'vprbench datasets verify gardens-point "
                                     f"--data-dir {data}' checks all of it."), str(error.value)
    assert verify_dataset("gardens-point", data).problems == [f"Dataset 'gardens-point': {said}"]
    with pytest.raises(VPRBenchError) as error:  # being imported: no command checks it but importing
        import_dataset("gardens-point", gardens, tmp_path / "other")
    assert str(error.value) == f"Dataset 'gardens-point': {said}"
