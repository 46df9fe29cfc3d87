"""Sessions on disk (docs/conventions.md section 3): loading and validation, schemas, the
calibration document (section 4) and the fingerprint of a session's inputs.
"""
