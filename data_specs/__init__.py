"""The toolkit's data files (class lists, vocabularies, the Replica mapping, schema prose).

This folder is installed as the package ``seggaussian.data_specs`` (see pyproject.toml) so that a wheel
carries it; code reads it through ``seggaussian.core.constants.DATA_SPECS_DIR``, never by a source-tree path.
"""
