"""The minimize-surprise method, free of I/O, and the little every package shares.

Networks and genome layout (:mod:`surprise.network`), the surprise fitness
(:mod:`surprise.fitness`), (1+1) online evolution as ask/tell (:mod:`surprise.evolution`), the
experiment configuration (:mod:`surprise.config`) and the wire protocol (:mod:`surprise.wire`).
Every package also uses its error tree (:mod:`surprise.errors`) and its one file writer
(:mod:`surprise.files`: atomic, with the permissions ``open()`` gives or private for secrets).
"""

__version__ = "0.1.0"
