"""Discrepancy analysis: where a recording departs from the nominal twin, which physics explains it
(a catalogued effect, or a generic block found by the discovery search), the fit with it, and what is
left unexplained (issues 6 and 12).

The package: ``twin`` (the recording's structure and the linear twin), ``registry`` (how each catalogue
effect is fitted, keyed by effect id: its regressors in both models, its parameters by name),
``noise`` (AR(1)+white noise, whitening, nulls), ``lrt`` (the nested tests and the line search),
``discovery`` (the dictionary of generic blocks and its change-point search), ``analysis`` (this
pipeline for recordings with table angles), ``attitude_free`` (recordings without), ``schema`` (the
result and the one finding schema).

The method, in the order :func:`analyze` runs it:

1. **Compare.** Fit the nominal model ``raw = M R^T v + b`` (physics/errorsep.py's joint fit) to every
   sample; the residuals are what the twin does not predict.
2. **Noise.** Estimate each axis's noise as AR(1) plus white (quantisation) from first differences of
   the residual inside the static holds (else every contiguous run of samples): a difference cancels
   any pose's mean, so slow model errors and drifts do not inflate it; the AR part only where the
   differences' autocorrelations show it (noise.ar_evidence). The data and every regressor are
   prewhitened with it (Kalman innovations).
3. **Linear twin.** Around the nominal fit the twin is linear in everything: the nominal Jacobian J0
   (M, b and two field-direction coordinates) plus, for each catalogue effect (physics/effects.py),
   regressor columns whose coefficients are the effect's parameters in its own units. The same
   machinery takes generic "unexplained structure" regressors (harmonics against each table angle,
   polynomials in time and temperature, the table rate, the accelerometer).
4. **Test.** Nested likelihood-ratio tests on the whitened data: the statistic of adding an effect's
   columns to the current model is chi-square with df = the rank they add. A parametric bootstrap
   (simulated AR(1) nulls at the recording's own time stamps, with the noise re-estimated each time,
   as the analysis does) measures how far the noise estimate inflates each statistic (a Bartlett
   factor). p-values are Bonferroni-corrected over every test of the round; no AIC. Mains pickup is a
   line search over frequency against the local spectrum (colour-robust), corrected for the number of
   independent frequencies.
5. **Name.** Forward selection: each round the catalogue's best effect and the dictionary's best block
   (physics/discrepancy/discovery.py) compete, each family held to its share of alpha, and the smaller
   p joins the model; a catalogue effect of implausible size is refused and its structure left to
   discovery; a backward check drops what is no longer significant given the rest; the twin is then
   relinearised around the nominal fit without the effects and checked again. Two effects are confusable when either
   one, once in the model, leaves the other insignificant; both are reported with the experiment that
   would separate them. Structure that no entry explains is reported as "unexplained structure against
   <input>". Effects the nominal model absorbs completely can only show as implausible or shifted
   nominal parameters ("parameter_shift").
6. **Model it.** Parameters with 1-sigma, residual RMS and heading error before and after, and the
   improvement on held-out data (4 interleaved folds of holds and 1-s chunks of motion); an effect that
   makes the held-out fit worse is left out, so the final model is never worse than the nominal one.

Pure numpy/scipy, no I/O.
"""

from physics.discrepancy.analysis import analyze, level_heading_error
from physics.discrepancy.schema import Analysis
from physics.discrepancy.twin import blocks, runs

__all__ = ["Analysis", "analyze", "blocks", "level_heading_error", "runs"]
