"""Implicit functions as data: the DAG, its parser, derivatives, evaluators.

expression (node, parser) -> derivatives (diff) -> evaluators (evaluate)
"""
from .diff import gradient, hessian, ray_derivatives
from .evaluate import evaluate, evaluate_interval, evaluate_with_error
from .node import Expr, const, var
from .parser import ParseError, parse

__all__ = ["Expr", "ParseError", "const", "evaluate", "evaluate_interval", "evaluate_with_error", "gradient",
           "hessian", "parse", "ray_derivatives", "var"]
