"""The studies the commands run besides the closed loop: the paper's scenarios (``paper``), the steady flow
(``flowtool``), the relaxation benchmark (``relaxation``), the stability map (``stabilitymap``), the extremes
(``extremes``), the speed-accuracy trade (``tradeoff``), the sort envelope's calibration (``calibrate``), and the
figures they draw (``figures``, ``painter``)."""
