"""One behavioural contract, run against every ``Body`` implementation (see ``bodies.py``)."""
