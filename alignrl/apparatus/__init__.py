"""Everything with a lens and an image: the Apparatus protocol, the synthetic SEM, the
image-quality algorithm, the scenario recorder and the CSV scenario simulator."""

from alignrl.apparatus.base import (
    Apparatus,
    ApparatusError,
    MeasurementError,
    NoEdgesError,
    SimulatedApparatus,
    check_write,
)
from alignrl.apparatus.quality import edge_width, measure_edges
from alignrl.apparatus.registry import make_apparatus, preset_names
from alignrl.apparatus.scenarios import ScenarioFormatError, ScenarioSet, read_scenarios
from alignrl.apparatus.simulator import ScenarioSimulator, default_scenarios_path
from alignrl.apparatus.synthetic import SEMConfig, SyntheticSEM

__all__ = [
    "Apparatus",
    "ApparatusError",
    "MeasurementError",
    "NoEdgesError",
    "SEMConfig",
    "ScenarioFormatError",
    "ScenarioSet",
    "ScenarioSimulator",
    "SimulatedApparatus",
    "SyntheticSEM",
    "check_write",
    "default_scenarios_path",
    "edge_width",
    "make_apparatus",
    "measure_edges",
    "preset_names",
    "read_scenarios",
]
