"""Parameter fitting (docs/ARCHITECTURE.md, ``fit``): the empirical
parameters of a technique (light size, biases, exponents, minimum variance, bleeding reduction,
filter sizes) fitted against the scene's Mitsuba ground truth.

* :mod:`.objective` — the loss: visibility RMSE in the truth's penumbra (default) or over every
  lit pixel, the truth's noise floor (mean σ² of its standard errors) subtracted, or mean FLIP of
  the shaded image; a Dr.Jit expression of the technique's visibility, so ``dr.backward`` reaches
  the technique's Dr.Jit parameters; kernel accounting through ``dr.kernel_history``.
* :mod:`.search` — windows and optimisers: ``mi.ad.Adam`` on reverse-mode gradients for
  parameters declared ``differentiable``, golden-section / exhaustive / grid search for the others,
  ``auto`` choosing per parameter from its declaration.
* :mod:`.preset` — named parameter sets (TOML/JSON) written by ``fit`` and read by
  ``compare --preset``.
* :mod:`.report` — ``fit.json``, ``summary.md``, ``preset.toml``, ``index.html`` with the loss
  history plot and before / after / truth images.
* :mod:`.run` — the ``shadowlab fit`` job (one technique or ``--all``).
* the fitting goals (Adam vs grid search) are measured by :mod:`shadowlab.bench.fit`.

>>> from shadowlab.fit import fit, Budget   # fit("parallel_planes", "pcss", out="reports/fit/pp")
"""

from .run import Budget, default_params, fit

__all__ = ["fit", "Budget", "default_params"]
