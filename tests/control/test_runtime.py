"""Taichi's start-up refusals, stopping on a signal between steps, and the statistics rows stacked."""
import inspect
import os
import signal

import numpy as np
import pytest
import taichi as ti

from ti_dk import ConfigError
from ti_dk.control.runtime import init, initialized, stats_of
from ti_dk.control.signals import Stopped, check_stop, stop_on_signals


def test_init_refuses_what_cannot_run():
    with pytest.raises(ConfigError, match="backend 'metal' is not supported"):
        init("metal")
    with pytest.raises(ConfigError, match="at least 1 CPU thread"):
        init("cpu", threads=0)
    assert initialized()  # the session's runtime (conftest) is untouched


def test_a_kernel_that_fails_to_compile_is_still_located():
    """init's plain source positions (no caret excerpt) keep the file, line and kernel."""
    line = inspect.currentframe().f_lineno + 4  # the line of the bad name

    @ti.kernel
    def broken() -> ti.i32:
        return undefined_name  # noqa: F821

    with pytest.raises(ti.TaichiNameError) as err:
        broken()
    assert f'File "{__file__}", line {line}, in broken' in str(err.value)
    assert "^" not in str(err.value)  # the caret excerpt is what init leaves out


def test_a_signal_stops_at_the_next_check_only():
    check_stop()  # no signal: nothing happens
    with stop_on_signals():
        os.kill(os.getpid(), signal.SIGTERM)  # the handler only sets a flag
        with pytest.raises(Stopped, match="stopped by SIGTERM at step 3") as err:
            check_stop(" at step 3")
    assert err.value.status == 143
    check_stop()  # the flag is cleared with the handlers
    with stop_on_signals():
        os.kill(os.getpid(), signal.SIGHUP)  # a closed terminal: the same as SIGTERM
        with pytest.raises(Stopped, match="stopped by SIGHUP") as err:
            check_stop()
    assert err.value.status == 129


def test_stats_of_stacks_rows_without_their_accumulators():
    rows = [{"mean": np.full(3, k), "variance": np.ones(3), "skewness": np.zeros(3), "kurtosis": np.zeros(3),
             "n_samples": np.int64(4), "acc_m2": np.ones(3)} for k in range(2)]
    st = stats_of(rows, None)
    assert st.mean.shape == (2, 3) and st.mean[1, 0] == 1 and st.n_samples.tolist() == [4, 4]
    assert st.histogram is None and st.hist_lo is None
