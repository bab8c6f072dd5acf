"""One capture end to end: the orchestrator, its outputs, videos, report.html."""
