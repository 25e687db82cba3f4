"""The paper's experiment (srl experiment paper): the grid of runs, the report and its plots."""
