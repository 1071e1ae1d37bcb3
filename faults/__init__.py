"""Communication faults as an experiment: link/agent fault specs, process chaos, evaluation sweeps."""
