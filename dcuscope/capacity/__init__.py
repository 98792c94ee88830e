"""``dcuscope capacity``: how many streams a pipeline takes on this machine within a latency budget.

The user's pipeline is run at 1, 2, ... streams (:mod:`.plan`), each count in its own process with
probes on (:mod:`.count`); each run's trace gives the figures of one count, with 95 % intervals
(:mod:`.measure`); bounds decide pass, fail or undecided (:mod:`.verdict`); two counts predict the
rest (:mod:`.predict`); the report is a table, Markdown, JSON (:mod:`.report`) and a plot
(:mod:`.plot`). :mod:`.search` runs the counts, :mod:`.command` is the command line.
"""
