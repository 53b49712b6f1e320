"""The Markdown of the reproduction report, rendered from the report dict (``report.json``).

:func:`~ga_ros.report.markdown.document.render_markdown` puts the sections in order; each
module renders the sections of one experiment (or family of experiments) of
:mod:`ga_ros.report.experiments`, reading only the report dict.
"""
