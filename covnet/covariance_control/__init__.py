"""The ``covariance_control`` scenario kind: covariance-control sensor allocation (the paper's
scenario), its fusion structures (central, information-matrix fusion, covariance intersection,
peer), slow links, and their experiments.  The kind registry's entry is :mod:`.kind`."""
