"""nanofrictor.identify: simulate, analyse and identify MEMS stick-slip friction runs."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("nanofrictor")
except PackageNotFoundError:  # a source tree that was never installed
    __version__ = "0+unknown"

from identify.diagnosis.rounds import DiagnosisOptions, DiagnosisResult, diagnose
from identify.fitting.driver import FitError, FitOptions, fit
from identify.fitting.parameters import Parameter, Parameters
from identify.fitting.result import FitResult
from identify.fitting.solver_options import GaussNewtonOptions, IpoptOptions, StopOptions
from identify.fitting.transient import TransientFitError, TransientRun, fit_transient
from identify.fitting.transient_result import TransientFitResult
from identify.model.laws import LAWS, get_law
from identify.model.params import (
    PARAMETER_SETS,
    SPECS,
    ParameterError,
    normal_load_from_voltage,
    parameter_set,
)
from identify.model.rsf import VelocityDrive, simulate_rsf
from identify.model.symbolic import Model
from identify.simulation.hybrid import RunConditions, SimulationOptions, SimulationResult, simulate, simulate_run
from identify.traces.analyze import AnalyzeResult, analyze
from identify.traces.events import RunEvents, extract_events
from identify.traces.force_cycles import CycleAnalysis, analyze_cycles, cycles_of_trace
from identify.traces.io import Trace, TraceFormatError, TraceSet, load_traces
from identify.traces.lab_import import detect_velocity_steps, import_run
from identify.traces.look import LookFormatError, read_look, read_mat, read_table
from identify.traces.look_recipe import apply_recipe
from identify.traces.reduced import reduced_fit

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
    "StopOptions",
    "GaussNewtonOptions",
    "IpoptOptions",
    "fit",
    "FitResult",
    "Parameter",
    "Parameters",
    "TransientRun",
    "TransientFitResult",
    "TransientFitError",
    "fit_transient",
    "VelocityDrive",
    "simulate_rsf",
    "read_look",
    "read_mat",
    "read_table",
    "CycleAnalysis",
    "analyze_cycles",
    "cycles_of_trace",
    "LookFormatError",
    "apply_recipe",
    "import_run",
    "detect_velocity_steps",
    "DiagnosisOptions",
    "DiagnosisResult",
    "diagnose",
]
