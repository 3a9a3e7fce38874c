"""The minimize-surprise method, free of I/O.

Networks and genome layout (:mod:`surprise.network`), the surprise fitness
(:mod:`surprise.fitness`), (1+1) online evolution as ask/tell (:mod:`surprise.evolution`), the
experiment configuration (:mod:`surprise.config`) and the wire protocol (:mod:`surprise.wire`).
"""

__version__ = "0.1.0"
