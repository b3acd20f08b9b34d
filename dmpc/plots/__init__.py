"""Figures of runs, drawn with matplotlib (imported lazily): the paper's five figures of a run or
comparison folder and the agents' solves per step of a run (:mod:`.report`, :mod:`.solves`,
``dmpc report``) and the figures of a ``dmpc.Result`` (:mod:`.result`, ``result.plot()``)."""
