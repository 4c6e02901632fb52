"""The dataset catalog (``DATASET/catalog.sqlite``): :mod:`embodmocap.catalog.db` builds and updates
it from the sessions' files and the batch's attempts; :mod:`embodmocap.catalog.views` prints the
summary, runs queries and writes ``catalog.parquet``."""
