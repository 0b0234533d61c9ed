"""Design models of the structures we build: the BORG truss (`borg`) and tetrahedral IPJR trusses
(`trusses`)."""
