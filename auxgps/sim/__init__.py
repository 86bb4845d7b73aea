"""The simulated world, its camera renderer and its flights. Used by evaluation and tests, never by the estimator."""
