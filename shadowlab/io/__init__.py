"""File input and output: EXR data images (named float32 channels), JSON metadata, sRGB PNG previews.

Modules: ``shadowlab.io.exr`` (``write_exr``, ``read_exr``, RGB channel helpers, ``check_finite``),
``shadowlab.io.jsonio`` (``write_json_atomic``, ``read_json``), ``shadowlab.io.png``, ``shadowlab.io.outdir``
(where a command may write: ``claim_dir``, ``write_dir``, ``check_out_file``, the report marker). Every writer is
atomic: it writes a temporary sibling file and renames it over the target with ``os.replace``.
"""
