"""Sessions on disk (docs/conventions.md section 3): the session's input types, loading and
validation, its tables and the calibration document (section 4). The schemas, names and
fingerprint they follow are the contract's (:mod:`fieldcal.contract`).
"""
