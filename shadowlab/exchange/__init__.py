"""Exchange with other renderers: export a scene (Mitsuba XML, PLY, camera / light JSON) and
ingest an image rendered elsewhere against the stored ground truth.

``export.export_scene`` (``shadowlab export SCENE --out DIR``) and ``ingest.ingest``
(``shadowlab ingest SCENE IMAGE.exr``); the conventions are in :mod:`.export`'s docstring and in
README.md, "Exchange with other renderers".
"""
