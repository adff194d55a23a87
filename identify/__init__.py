"""nanofrictor.identify: simulate, analyse and identify MEMS stick-slip friction runs."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("nanofrictor")
except PackageNotFoundError:  # a source tree that was never installed
    __version__ = "0+unknown"

from .analyze import AnalyzeResult, analyze
from .diagnosis import DiagnosisOptions, DiagnosisResult, diagnose
from .events import RunEvents, extract_events
from .fit import FitError, FitOptions, fit
from .laws import LAWS, get_law
from .model import Model
from .params import (
    PARAMETER_SETS,
    SPECS,
    ParameterError,
    normal_load_from_voltage,
    parameter_set,
)
from .reduced import reduced_fit
from .report import FitResult
from .simulation import RunConditions, SimulationOptions, SimulationResult, simulate, simulate_run
from .traces import Trace, TraceFormatError, TraceSet, load_traces

__all__ = [
    "__version__",
    "LAWS",
    "get_law",
    "Model",
    "PARAMETER_SETS",
    "SPECS",
    "ParameterError",
    "normal_load_from_voltage",
    "parameter_set",
    "RunConditions",
    "SimulationOptions",
    "SimulationResult",
    "simulate",
    "simulate_run",
    "Trace",
    "TraceFormatError",
    "TraceSet",
    "load_traces",
    "RunEvents",
    "extract_events",
    "reduced_fit",
    "AnalyzeResult",
    "analyze",
    "FitError",
    "FitOptions",
    "fit",
    "FitResult",
    "DiagnosisOptions",
    "DiagnosisResult",
    "diagnose",
]
