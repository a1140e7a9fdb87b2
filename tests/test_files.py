"""c4d_core.files: writes through a temporary sibling never leave a half-written or lost file."""

import errno
import json

import numpy as np
import pytest

from c4d_core.errors import UserError
from c4d_core.files import atomic_path, write_json, write_text


def test_atomic_path_renames_into_place_and_creates_the_folder(tmp_path):
    target = tmp_path / "new" / "depth.png"
    with atomic_path(target) as tmp:
        assert tmp.parent == target.parent and tmp.suffix == ".png" and tmp.name.startswith(".")
        tmp.write_bytes(b"complete")
    assert target.read_bytes() == b"complete"
    assert sorted(p.name for p in target.parent.iterdir()) == ["depth.png"]


def test_a_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path):
    target = write_text(tmp_path / "report.md", "old report\n")
    with pytest.raises(RuntimeError, match="writer crashed"):
        with atomic_path(target) as tmp:
            tmp.write_text("half of the new rep")
            raise RuntimeError("writer crashed")
    assert target.read_text() == "old report\n"
    assert [p.name for p in tmp_path.iterdir()] == ["report.md"]


def test_disk_full_becomes_one_user_error_naming_the_file(tmp_path):
    target = write_text(tmp_path / "eval.json", "{}\n")
    with pytest.raises(UserError) as info:
        with atomic_path(target):
            raise OSError(errno.ENOSPC, "No space left on device")
    message = str(info.value)
    assert message.startswith("no space left") and str(target) in message
    assert "run the same command again" in message
    assert target.read_text() == "{}\n"


def test_a_writers_own_error_without_errno_is_kept(tmp_path):
    with pytest.raises(OSError, match="cannot encode") as info:
        with atomic_path(tmp_path / "tracks.webm"):
            raise OSError("OpenCV cannot encode .webm here")
    assert not isinstance(info.value, UserError)
    assert list(tmp_path.iterdir()) == []


def test_write_json_round_trips_numpy_values(tmp_path):
    value = {"ate": np.float32(0.25), "counts": np.arange(3), "steps": np.int64(7), "path": tmp_path}
    path = write_json(tmp_path / "metrics.json", value)
    assert json.loads(path.read_text()) == {"ate": 0.25, "counts": [0, 1, 2], "steps": 7,
                                            "path": str(tmp_path)}
