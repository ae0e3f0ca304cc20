"""Decision rules: per-cell registrations of a pair -> AM / RM / NM."""

from artclass_core import hookimpl

from .paper import PaperRule
from .robust import RobustRule


@hookimpl
def register_rules(register):
    register(PaperRule)
    register(RobustRule)
