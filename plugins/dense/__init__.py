"""Dense, image-space motion evidence: the default pipeline.

- ``image`` preprocessor (:mod:`.image`): the masked depth as an organised cloud, filtered on image
  neighbourhoods;
- ``dense`` registrar (:mod:`.registrar`): rigid-motion hypotheses for the whole pair and every
  point's evidence;
- ``dense`` rule (:mod:`.rule`): how many motions the evidence needs, by model selection.

Each registers with the built-ins of its kind (``artclass_plugins.preprocessors``, ``.registrars``,
``.rules``), so ``ARTCLASS_PLUGINS`` switches them with their kind.
"""
