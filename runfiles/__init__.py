"""The run directory's files, as one typed schema shared by every writer and reader.

Nothing is imported here, so that each part costs only what it uses.
"""
