"""The minimize-surprise method, free of I/O, and the little every package shares.

Networks and genome layout (:mod:`minimize_surprise.network`), the surprise fitness
(:mod:`minimize_surprise.fitness`), (1+1) online evolution as ask/tell
(:mod:`minimize_surprise.evolution`), the experiment configuration (:mod:`minimize_surprise.config`)
and the wire protocol (:mod:`minimize_surprise.wire`). Every package also uses its error tree
(:mod:`minimize_surprise.errors`) and its one file writer (:mod:`minimize_surprise.files`: atomic,
with the permissions ``open()`` gives or private for secrets).
"""

__version__ = "0.1.0"
