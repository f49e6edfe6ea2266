"""Mitsuba 3 clients: the library's optimizers in Mitsuba's own loops and scenes
(docs/mitsuba.md). ``common`` and ``runner`` are what the experiments here share."""
