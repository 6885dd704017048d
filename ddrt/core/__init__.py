"""Computation: the dynamic model, the motor model, the Kalman filters and the estimator, the
controllers and online adaptation, and the small types they exchange. Pure: imports no
driver, no service and no simulator."""
