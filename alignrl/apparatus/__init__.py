"""Everything with a lens and an image: the Apparatus protocol and its capabilities, the
synthetic SEM, the image-quality algorithm, the safety shield, the scenario recorder and the
CSV scenario simulator."""

from alignrl.apparatus.base import (
    Apparatus,
    ApparatusError,
    BatchedQueries,
    KnowsBestQuality,
    KnowsOptimum,
    MeasurementError,
    MeasuresDirectional,
    MeasuresWobble,
    NoEdgesError,
    ReportsApplied,
    SimulatedApparatus,
    answers_batched,
    check_write,
    knows_best_quality,
    knows_optimum,
    offers_directional,
    offers_wobble,
    reports_applied,
)
from alignrl.apparatus.quality import edge_width, measure_edges
from alignrl.apparatus.registry import make_apparatus, make_apparatus_copies, preset_names
from alignrl.apparatus.scenarios import ScenarioFormatError, ScenarioSet, read_scenarios
from alignrl.apparatus.simulator import ScenarioSimulator, default_scenarios_path
from alignrl.apparatus.synthetic import SEMConfig, SyntheticSEM

__all__ = [
    "Apparatus",
    "ApparatusError",
    "BatchedQueries",
    "KnowsBestQuality",
    "KnowsOptimum",
    "MeasurementError",
    "MeasuresDirectional",
    "MeasuresWobble",
    "NoEdgesError",
    "ReportsApplied",
    "SEMConfig",
    "ScenarioFormatError",
    "ScenarioSet",
    "ScenarioSimulator",
    "SimulatedApparatus",
    "SyntheticSEM",
    "answers_batched",
    "check_write",
    "default_scenarios_path",
    "edge_width",
    "knows_best_quality",
    "knows_optimum",
    "make_apparatus",
    "make_apparatus_copies",
    "measure_edges",
    "offers_directional",
    "offers_wobble",
    "preset_names",
    "read_scenarios",
    "reports_applied",
]
