"""The thermal loop: the spindle's growth from temperatures, and the effects a linear model lacks.

data (the rows), start (cold starts, several runs), terms and candidates, fit (least squares,
forward errors), model (saved, predicted live), selection, residual, baselines, loop (analyze),
refit (the daemon's). Pure numpy/scipy, no asyncio. See docs/thermal.md.
"""
from lathed.analysis.forward import improvement_z, rmse
from lathed.analysis.thermal.baselines import baseline_stages, fit_stage
from lathed.analysis.thermal.candidates import (AmbientLagCandidate, Candidate, DriftCandidate, HysteresisCandidate,
                                                LagCandidate, NonlinearCandidate, PeriodicCandidate, RateCandidate,
                                                SpeedCandidate, SpeedLagCandidate, SpeedStepCandidate,
                                                SpeedTempCandidate, builtin_candidates)
from lathed.analysis.thermal.data import ThermalData, ThermalRuns, sensor_column, smooth_rows, split_run
from lathed.analysis.thermal.fit import design, fit_coefficients, fit_design, forward_errors
from lathed.analysis.thermal.loop import analyze, describe
from lathed.analysis.thermal.model import (ThermalModel, ThermalPredictor, eq14_model, load_model,
                                           save_model)
from lathed.analysis.thermal.refit import RefitResult, refit
from lathed.analysis.thermal.report import Analysis, EffectFound, SensorKept, Stage
from lathed.analysis.thermal.residual import ResidualReport, residual_structure
from lathed.analysis.thermal.selection import select_sensors
from lathed.analysis.thermal.start import join_runs, reference_test
from lathed.analysis.thermal.terms import (AmbientLagTerm, DriftTerm, HysteresisTerm, LagTerm, LinearTerm,
                                           NonlinearTerm, PeriodicTerm, RateTerm, SpeedLagTerm, SpeedStepTerm,
                                           SpeedTempTerm, SpeedTerm, Term, lag_filter, play_operator)

__all__ = [n for n in dir() if not n.startswith("_")]
