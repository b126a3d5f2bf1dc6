"""The live view and recordings: the `live` extra (pip install 'drvs[live]'): the Foxglove hub
and its token gate, the Foxglove client, drvs-replay. Its libraries load only when a view starts."""
