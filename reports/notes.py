"""Notes a report part wants shown in the report's index (``results/PROFILE/README.md``).

A part calls ``warnings.warn(message, ReportNote)``; :func:`reports.main.run_report`
records every :class:`ReportNote` (and every Mitsuba backend fallback warning) raised
while the part runs, prints it, and lists it under the part in the index.
"""


class ReportNote(UserWarning):
    """A remark for the report's index: cached results reused, a backend missing, a part skipped."""
