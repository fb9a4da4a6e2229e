"""What a run leaves behind and how it is shown: the MCAP recording (``mcap``, with Foxglove's messages and vcyto's
schemas), the Rerun view (``rerunlog``, ``viewer``) and its replay (``replay``), the sinks' thread (``sinks``), FCS
and Gating-ML export (``fcs``, ``gatingml``), and where a run's files go and how they are finished (``runfiles``)."""
