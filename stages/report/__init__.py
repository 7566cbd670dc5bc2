"""The run report: one self-contained HTML page to judge a run (``write.report``)."""
