"""What only the whole scene says (scene/checks.py): each case a one-line refusal, or taken."""
import warnings

import numpy as np
import pytest

from ti_dk import ConfigError, load_scene


def _refused(match, scene="void1d", **overrides):
    with pytest.raises(ConfigError, match=match) as err:
        load_scene(scene, **overrides)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("potential", ["20*step(x-0.5)", "3*abs(x-0.5)", "x**2 + 0.5*step(x-0.2)"])
def test_a_potential_with_a_jump_or_kink_is_refused_for_the_walk_and_taken_by_the_spde(potential):
    """The walk moves by −½∇U alone: it would not see the jump fv follows through e^{−U}."""
    kink = "step" if "step" in potential else "abs"
    for method in ("particle", "hybrid"):
        _refused(rf"{kink}\(\) has a jump or kink .* method {method} moves particles by the drift -grad\(U\)/2 "
                 r"alone, so it would not follow e\^\(-U\) there as fv does; .* use method fv or gaussian", "trap1d", potential=potential, init="uniform", method=method)
    _refused("method particle moves", "trap1d", potential=potential, init="uniform", compare="particle")
    for method in ("fv", "gaussian"):
        assert load_scene("trap1d", potential=potential, init="uniform", method=method).potential is not None
    assert load_scene("trap1d", potential="20*(1+tanh((x-0.5)/0.02))/2", init="uniform", method="particle")


@pytest.mark.parametrize("potential, axis, jump", [("5*x", 0, "5"), ("sin(2*pi*x) + y", 1, "1"),
                                                   ("3*x + x*sin(2*pi*y)", 0, r"3\.2")])
def test_a_potential_not_periodic_on_a_periodic_axis_is_refused_naming_the_axis_and_the_jump(potential, axis, jump):
    dim = 1 + ("y" in potential)
    x = "xy"[axis]
    _refused(rf"not periodic along axis {axis} \({x}\), whose sides are periodic: .*a jump of {jump}\); give a "
             "potential with the same value at both ends", "trap1d", potential=potential, init="uniform",
             boundary="periodic", cells=[16] * dim)
    # the same potential with that axis closed is taken; a periodic one on periodic axes too
    closed = ["periodic"] * dim
    closed[axis] = "neumann"
    load_scene("trap1d", potential=potential, init="uniform", boundary=closed, cells=[16] * dim)
    load_scene("trap1d", potential="cos(2*pi*x) + 3", init="uniform", boundary="periodic", method="particle")


@pytest.mark.parametrize("key", ["buffer", "min_box"])
def test_the_hybrids_sizes_are_bounded_by_the_grid(key):
    """buffer = 1e9 on 16 cells hung (the region grew one cell at a time)."""
    _refused(f"{key} = 1,000,000,000: give at most 16, the most cells along an axis", cells=[16],
             method="hybrid", **{key: 10**9}, **({"max_box": 2 * 10**9} if key == "min_box" else {}))
    assert load_scene("void1d", cells=[16], method="hybrid", **{key: 16}, max_box=32).hybrid.buffer >= 0




@pytest.mark.parametrize("density", ["1e300+0*x", "1e200", "1e16", "1e16*step(x-0.9)"])
def test_a_density_beyond_any_particle_count_is_refused_naming_the_limit(density, tmp_path):
    _refused(r"density: the initial density is 1e\+\d+ in cell \[\d+\]: give finite densities in \[0, 1e\+15\]",
             init="expression", density=density, cells=[16])
    np.save(tmp_path / "q.npy", np.full(16, float(density.split("+")[0].split("*")[0])))
    _refused(r"density_file: the initial density is 1e\+\d+ .* \[0, 1e\+15\]", init="array",
             density_file=str(tmp_path / "q.npy"), cells=[16])
    assert load_scene("void1d", init="expression", density="1e15", cells=[16]).initial_ppc.max() == 1e15


def test_a_boltzmann_density_piled_beyond_any_particle_count_is_refused():
    _refused("potential: the initial density is .* give finite densities in", "trap1d", ppc=1e15,
             potential="0.5*((x-0.5)/0.01)**2", cells=[64], C=0.01)


@pytest.mark.parametrize("overrides, said", [
    (dict(reservoir_ppc=5), r"reservoir_ppc on axis 0 does nothing on its lower side \(periodic, 5 given\) and upper "
                            r"side \(periodic, 5 given\): only dirichlet sides have a reservoir"),
    (dict(boundary=[["dirichlet", "neumann"]], reservoir_ppc=[[1, 2]]), r"upper side \(neumann, 2 given\):"),
    (dict(ensemble=1, t_equil=0.009, sample_every=1000), "pools one step of one member: the row's variance, skewness"),
    (dict(ensemble=1, structure_factor=True), "structure_factor = true with one member and no t_equil: every row is "
                                              "one sample, so S.k. is not defined and none is drawn")])
def test_keys_that_do_nothing_for_the_scene_are_said_to(overrides, said):
    from ti_dk.scene.load import InputWarning

    with pytest.warns(InputWarning, match=said) as caught:
        load_scene("void1d", output_times=[], **overrides)
    assert len(caught) == 1 and caught[0].filename == __file__  # said once, at the caller's line
    taken = {"reservoir_ppc": dict(boundary="dirichlet"), "sample_every": dict(sample_every=100),
             "structure_factor": dict(ensemble=2)}[next(k for k in ("reservoir_ppc", "sample_every",
                                                                  "structure_factor") if k in overrides)]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_scene("void1d", output_times=[], **(overrides | taken))


def test_t_end_below_one_step_is_refused_as_the_docs_say():
    dt = load_scene("void1d").dt
    _refused(r"t_end = 3.75e-06 is shorter than one time step dt = 6.25e-06: raise t_end", t_end=0.6 * dt)
    assert load_scene("void1d", t_end=dt, output_times=[]).n_steps == 1
