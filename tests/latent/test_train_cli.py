"""train_latent.py's user mistakes: each gives one line on stderr that names the option or file and the problem, and
exit status 2, before anything is trained or written (called in-process through ``main(argv)``)."""
from pathlib import Path

import pytest

from train_latent import main

from .spheres import sphere_scans

TINY = ["--latent-dim", "2", "--width", "16", "--depth", "1", "--epochs", "1", "--quiet"]


@pytest.fixture
def collection(tmp_path):
    """A collection of four training spheres (no validation split)."""
    from datasets.collection import ScanCollection

    path = tmp_path / "spheres.h5"
    ScanCollection.create(path, sphere_scans())
    return path


def _refused(argv, capsys):
    """Run the command line, check it refused with exit status 2 and one error line (no traceback, nothing on
    stdout); return that line."""
    capsys.readouterr()
    assert main([str(a) for a in argv]) == 2
    out, err = capsys.readouterr()
    lines = err.splitlines()
    assert out == "" and len(lines) == 1, err
    assert lines[0].startswith("error: ") and "Traceback" not in err
    return lines[0]


@pytest.mark.parametrize("option, value, problem", [
    ("--epochs", "-3", ">= 1"), ("--epochs", "0", ">= 1"), ("--latent-dim", "0", ">= 1"), ("--width", "-1", ">= 1"),
    ("--depth", "0", ">= 1"), ("--batch", "0", ">= 1"), ("--samples", "0", ">= 1"), ("--lr", "0", "> 0"),
    ("--code-lr", "-0.001", "> 0"), ("--calibration-fraction", "1", "[0, 1)"), ("--checkpoint-every", "-1", ">= 0"),
    ("--threads", "-1", ">= 0"), ("--representation", "voxels", "invalid choice"), ("--device", "tpu", "invalid choice"),
    ("--calibration-folds", "1", "0 (none) or >= 2"), ("--calibration-folds", "-2", "0 (none) or >= 2"),
    ("--epochs", "ten", "invalid int value"), ("--lr", "fast", "invalid float value")])
def test_a_bad_option_value_is_one_line_naming_the_option_and_the_value(collection, tmp_path, capsys, option, value,
                                                                        problem):
    out = tmp_path / "model.pt"
    line = _refused(["--data", collection, "--out", out, option, value], capsys)
    assert option in line and value in line and problem in line
    assert not out.exists()


def test_a_missing_or_unknown_option_is_one_line_naming_it(collection, tmp_path, capsys):
    line = _refused(["--data", collection], capsys)
    assert "required" in line and "--out" in line
    line = _refused(["--data", collection, "--out", tmp_path / "model.pt", "--seeds", "3"], capsys)
    assert "unrecognized arguments: --seeds 3" in line


def test_a_data_file_that_is_missing_or_no_collection_is_one_line_naming_it(tmp_path, capsys):
    import h5py

    out = tmp_path / "model.pt"
    line = _refused(["--data", tmp_path / "nope.h5", "--out", out], capsys)
    assert f"{tmp_path / 'nope.h5'}: no such scan collection" in line
    line = _refused(["--data", tmp_path, "--out", out], capsys)
    assert f"{tmp_path}: is a folder" in line
    junk = tmp_path / "junk.h5"
    junk.write_text("junk")
    assert f"{junk}: not an HDF5 file" in _refused(["--data", junk, "--out", out], capsys)
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f["x"] = [1, 2, 3]
    assert f"{other}: an HDF5 file but not a scan collection" in _refused(["--data", other, "--out", out], capsys)
    assert not out.exists()


def test_a_collection_without_good_scans_to_train_on_is_one_line(collection, tmp_path, capsys):
    line = _refused(["--data", collection, "--out", tmp_path / "model.pt", "--split", "validation"], capsys)
    assert f"{collection}: no good scans in split 'validation'" in line


def test_an_existing_output_needs_overwrite_or_resume(collection, tmp_path, capsys):
    out = tmp_path / "model.pt"
    out.write_text("an earlier result")
    line = _refused(["--data", collection, "--out", out, *TINY], capsys)
    assert f"{out}: already exists" in line and "--overwrite" in line and "--resume" in line
    assert out.read_text() == "an earlier result"  # untouched
    line = _refused(["--data", collection, "--out", out, "--resume", *TINY], capsys)  # not a checkpoint to resume
    assert f"{out}: not a readable latent model checkpoint" in line
    assert out.read_text() == "an earlier result"


def test_an_output_that_is_a_folder_or_inside_a_file_is_one_line(collection, tmp_path, capsys):
    folder = tmp_path / "results"
    folder.mkdir()
    for extra in ([], ["--overwrite"]):
        line = _refused(["--data", collection, "--out", folder, *TINY, *extra], capsys)
        assert f"{folder}: is a folder" in line
    blocker = tmp_path / "notes.txt"
    blocker.write_text("a file, not a folder")
    line = _refused(["--data", collection, "--out", blocker / "model.pt", *TINY], capsys)
    assert f"{blocker / 'model.pt'}: cannot be written" in line and f"{blocker} is a file" in line


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux's /proc (a folder no file can be made in)")
def test_an_output_in_a_folder_no_file_can_be_written_in_is_one_line(collection, capsys):
    line = _refused(["--data", collection, "--out", "/proc/model.pt", *TINY], capsys)
    assert "/proc/model.pt: cannot be written" in line and "folder /proc" in line
