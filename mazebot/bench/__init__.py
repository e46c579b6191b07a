"""The benchmark harness: whole simulated runs on virtual time, measured against ground truth."""
