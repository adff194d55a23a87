"""The mode sequence: which step triggers each slip, decided by the data.

The detector's sequence (:mod:`identify.traces.events`) is where a fit starts; these
modules change it where the model says it is wrong, each change re-solved and kept only
when the data pay for it:

* :mod:`~identify.fitting.mode_sequence.triggers`: each slip's trigger scored at its
  neighbouring steps, and the trigger residual (a mixin of the problem);
* :mod:`~identify.fitting.mode_sequence.missed`: slips the detection missed;
* :mod:`~identify.fitting.mode_sequence.passes`: the passes that try changes against
  the whole model (a run's many late triggers in one trial, the detector's ambiguous
  triggers, local changes where triggers misfit);
* :mod:`~identify.fitting.mode_sequence.trials` and
  :mod:`~identify.fitting.mode_sequence.carry`: a trial solved and a changed sequence
  carried into a new problem;
* :mod:`~identify.fitting.mode_sequence.decide`: the order of all of it
  (:func:`~identify.fitting.mode_sequence.decide.decide_sequence`).

Which passes run is ``FitOptions.sequence_passes``. Nothing is imported here: the
problem imports the trigger mixin from this package, and the other modules import the
problem.
"""
