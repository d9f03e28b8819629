"""The ``units`` attribute of every dataset of a run file (:class:`ti_dk.output.files.RunFile`).

Conventions: lengths in the scene's unit L, times in L²/(2D) (the particles diffuse with D = ½, so
one unit of time is L²); ``/stats`` moments are of the number density, particles per unit volume
(L^-d in d dimensions; multiply by the group's ``cell_volume`` for particles per cell), while
histograms and frames count particles per cell; per-step diagnostics and regrid records of an
ensemble are sums over its members (``min_density``: the minimum), frames show member 0.
"""
from __future__ import annotations

SUM = " (sum over members)"
UNITS = {
    "stats/time": "L^2/(2D) (the time of the row)",
    "stats/n_samples": "densities pooled into the row (members x time samples)",
    "stats/mean": "particles per unit volume (L^-d)",
    "stats/variance": "(particles per unit volume)^2 (L^-2d); unbiased, over the row's samples",
    "stats/skewness": "dimensionless: k3 / k2^(3/2)",
    "stats/kurtosis": "dimensionless, non-excess: k4 / k2^2 + 3 (3 for a Gaussian)",
    "stats/histogram": "samples per bin; bin k: lo + k particles per cell (attribute lo)",
    "stats/histogram_outside": "samples outside the histogram's bins",
    "stats/structure_factor": "dimensionless: <|sum_j dN_j e^(-ik.x_j)|^2> / <N_total> (attribute definition)",
    "diagnostics/time": "L^2/(2D) (the end of the step)",
    "diagnostics/mass": "particles" + SUM,
    "diagnostics/min_density": "particles per unit volume (L^-d); minimum over members and cells",
    "diagnostics/negative_cells": "cells with negative density" + SUM,
    "diagnostics/boundary_inflow": "particles entering minus leaving through Dirichlet sides in the step" + SUM,
    "diagnostics/clamped_steps": "particle steps clamped to +-dx along an axis in the step (hybrid: of its particles and the ghosts that enter)" + SUM,
    "diagnostics/particles": "particles in the particle region" + SUM,
    "diagnostics/regrid_change": "particles created minus removed by the step's regrid" + SUM,
    "regrid/step": "the step after which the region was made",
    "regrid/boxes": "boxes" + SUM,
    "regrid/covered_cells": "cells" + SUM,
    "regrid/efficiency": "tagged / covered cells, over all members (tagged: the cells below threshold, before "
                         "the buffer)",
    "regrid/created": "particles sampled into newly covered cells" + SUM,
    "regrid/removed": "particles removed from cells no longer covered" + SUM,
    "regrid/on_demand": "members regridded off schedule (0: a scheduled regrid of all)",
    "frames/time": "L^2/(2D) (the time of the frame)",
    "series/time": "L^2/(2D) (the time of the record)",
    "series/mass": "particles, per member",
    "series/negative_cells": "cells with negative density, per member",
    "series/particles": "particles in the particle region, per member",
    "series/region_cells": "cells of the particle region, per member",
    "observables/time": "L^2/(2D) (the time of the record)",
    "frames/negative_cells": "cells with negative density in member 0's frame",
}


def units_of(path: str) -> str | None:
    """The ``units`` attribute of the dataset at ``path`` (``group/name``); None for one not listed."""
    group, name = path.strip("/").split("/", 1)
    if group == "observables" and name != "time":  # the scene's own names
        return "particles in the region (cells whose centre satisfies its condition), per member"
    if name.startswith("compare_"):
        plain = units_of(f"{group}/{name[len('compare_'):]}")
        return plain and f"{plain}; of the compared method"
    return UNITS.get(f"{group}/{name}")
