"""The synthetic face of the fixture performer: a 3D-aware procedural face, expression
controls, geometry-driven expression details and a pinhole renderer (docs/fixtures.md).
``train.eigenfeatures`` renders it to train on a fixture pack's performer (:mod:`..synthetic`);
the fixture generator (``lab.facegen``, ``scripts/make_fixtures.py``) makes the packs and clips with it."""
