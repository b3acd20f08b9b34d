"""Figures of runs, drawn with matplotlib (imported lazily): the paper's five figures of a run or
comparison folder (:mod:`.report`, ``dmpc report``) and the figures of a ``dmpc.Result``
(:mod:`.result`, ``result.plot()``)."""
