"""The PDP benchmark: evaluation protocol, baselines and figures."""
