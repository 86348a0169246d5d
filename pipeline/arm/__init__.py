"""The arm: the simulated 3-chamber arm, the safe set of commands, the exploration walk."""
