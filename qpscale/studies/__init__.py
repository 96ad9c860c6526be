"""Studies built on the experiments: the paper's figures (paper*.py) and the solver benchmark (bench*.py)."""
