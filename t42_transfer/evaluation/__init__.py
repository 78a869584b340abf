"""Evaluation of dynamics models: open-loop accuracy (:mod:`.metrics`) and Lyapunov exponents (:mod:`.lyapunov`).

Nothing is imported here so that ``import t42_transfer.evaluation`` stays cheap;
import the submodules directly.
"""
