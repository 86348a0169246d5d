"""Evaluation: closed-loop rollouts, MPC, metrics, figures and the report."""
