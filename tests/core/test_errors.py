"""The errors ti_dk raises live in one module, and the public API and the modules that raise them
name those same classes."""
import ti_dk
from ti_dk.control import signals
from ti_dk.core import errors, expr
from ti_dk.output import files
from ti_dk.scene import schema


def test_every_error_class_is_the_one_in_core_errors():
    assert (ti_dk.ConfigError, ti_dk.OutputError, ti_dk.SimulationError) == (
        errors.ConfigError, errors.OutputError, errors.SimulationError)
    assert schema.ConfigError is errors.ConfigError and files.OutputError is errors.OutputError
    assert signals.Stopped is errors.Stopped and expr.ExprError is errors.ExprError
    assert issubclass(errors.Stopped, ti_dk.SimulationError)
    assert errors.Stopped("stopped", 143).status == 143
