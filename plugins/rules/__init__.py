"""Decision rules: per-cell registrations of a pair -> AM / RM / NM."""

from artclass_core import hookimpl

from ..dense.rule import DenseRule
from .paper import PaperRule


@hookimpl
def register_rules(register):
    register(DenseRule)
    register(PaperRule)
