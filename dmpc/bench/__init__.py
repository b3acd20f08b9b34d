"""``dmpc bench``: what it measures (:mod:`.measures`), the bus's own floor (:mod:`.floor`), the
scale table (:mod:`.scale`) and the report of them all (:mod:`.results`)."""
