"""`ddrt sweep`: campaigns of simulated runs on Dask (the `sweep` extra: dask[distributed], pyarrow).

A campaign file (campaign.py) expands into cases, each a validated config and a built path
(cases.py); they run where Dask puts them, or in this process (execute.py, run.py); each row
is journalled as it finishes (journal.py) and the rows become a Parquet/CSV table
(table.py), a summary (summary.py) and figures (figures.py). The robot populations a
campaign can draw come from population.py, which bench/population.py shares.

Nothing outside ddrt.cli and ddrt.docgen (for reference.py) imports this package, and then
only when it is used; it imports dask and pyarrow only where it uses them, so `ddrt sim`
never loads them.
"""
