"""Estimate: the estimators run on each vehicle's samples (pipeline) and the live
comparison of their output with the references (compare). May import ``wire`` and
``vehicle``. A new estimator is registered in ``estimators/``, not here."""
