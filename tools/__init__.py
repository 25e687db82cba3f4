"""Tools above the services: the srl command, the launcher, health checks, benchmarks, the experiment, plots."""
