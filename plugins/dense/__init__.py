"""Dense, image-space motion evidence: the default pipeline.

- ``image`` preprocessor: the masked depth as an organised cloud, filtered on image neighbourhoods;
- ``dense`` registrar: rigid-motion hypotheses for the whole pair and every point's evidence;
- ``dense`` rule: how many motions the evidence needs, by model selection.
"""

from artclass_core import hookimpl

from .image import ImagePreprocessor
from .registrar import DenseRegistrar
from .rule import DenseRule


@hookimpl
def register_preprocessors(register):
    register(ImagePreprocessor)


@hookimpl
def register_registrars(register):
    register(DenseRegistrar)


@hookimpl
def register_rules(register):
    register(DenseRule)
