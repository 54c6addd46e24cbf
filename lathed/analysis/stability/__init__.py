"""The stability loop (docs/stability.md): the model of the lobes
(``model``), what it gets wrong on recorded cuts (``residual``), the effects it
may lack (``effects``) and the residual loop that adds them (``refit``); a
model learned from the cuts alone, with how sure it is (``start``, ``learn``);
adopted models on disk (``files``); synthetic cut sets for tests and
benchmarks (``cases``)."""
from lathed.analysis.stability.model import StabilityModel, limit_depth
from lathed.analysis.stability.refit import Refit, refit
from lathed.analysis.stability.residual import Residual, residual

__all__ = ["StabilityModel", "limit_depth", "Refit", "refit", "Residual", "residual"]
