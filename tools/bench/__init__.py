"""Benchmarks: srl bench actor | loop | bridge (each prints a table and, with --json, one JSON line)."""
