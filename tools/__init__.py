"""Tools above the services: the srl command (commands/), the launcher (launch/), recordings and the
live view (recording/), benchmarks (bench/), the experiment (experiment/), the generated docs (docs/)."""
