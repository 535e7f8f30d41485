"""Result files: written atomically, with the permissions of a directly created file."""

import os
import stat

import pytest

from eyefem.io.output import write_csv, write_text


@pytest.mark.parametrize("umask", [0o022, 0o077])
def test_result_files_get_the_umask_permissions_and_no_temporary_is_left(tmp_path, umask):
    old = os.umask(umask)
    try:
        write_text(tmp_path / "summary.json", "{}")
        write_csv(tmp_path / "history.csv", [{"t": 0.5, "iop": 15.0}])
    finally:
        os.umask(old)
    for name in ("summary.json", "history.csv"):
        mode = stat.S_IMODE((tmp_path / name).stat().st_mode)
        assert mode == 0o666 & ~umask, (name, oct(mode))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["history.csv", "summary.json"]
    assert (tmp_path / "history.csv").read_text().splitlines() == ["t,iop", "0.5,15"]


def test_a_failed_write_leaves_neither_the_file_nor_a_temporary(tmp_path):
    class Boom(Exception):
        pass

    from eyefem.io.output import atomic_path

    with pytest.raises(Boom):
        with atomic_path(tmp_path / "field.vtu") as tmp:
            tmp.write_text("half")
            raise Boom
    assert list(tmp_path.iterdir()) == []
