"""The run options that are not scene keys: checked before anything starts, each refusal one line."""
import pytest

from ti_dk import ConfigError, load_scene
from ti_dk.control.options import check_options


def test_options_are_checked_before_anything_starts(tmp_path):
    s = load_scene("void1d", ensemble=2)
    check_options(s, out=tmp_path / "new" / "dir", executor="dask", workers=2, chunk=1)
    (tmp_path / "f").write_text("")
    for kw, msg in [(dict(out=tmp_path / "f"), "is a file"), (dict(threads=0), "--threads = 0"),
                    (dict(executor="dask", workers=0), "--workers = 0"), (dict(chunk=3), "--chunk is for"),
                    (dict(restart=tmp_path / "none.h5"), "no such checkpoint")]:
        with pytest.raises(ConfigError, match=msg):
            check_options(s, **kw)
