"""The live view: a web page that watches a running or finished run (``dmpc watch``).

The plant publishes each completed step on a telemetry key (:mod:`.telemetry`); an observer
collects the steps of a run from the bus (:mod:`.observer`) or from its run folder
(:mod:`.folder`) into one :class:`~.state.RunState`, and a Bokeh server shows it
(:mod:`.page`, :mod:`.server`). Only :mod:`.meta` and :mod:`.telemetry` are imported by the
plant; they need neither Bokeh nor a web server.
"""
