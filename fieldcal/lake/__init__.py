"""The versioned data lake: storage, commits and history queries.
"""
