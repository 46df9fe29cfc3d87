"""Sessions on disk (CONTRACT section 3): loading and validation, schemas, the
calibration document (section 4) and the fingerprint of a session's inputs.
"""
