"""Where mfvs's own files are: the repository it runs from (its services' processes start there) and the
directories its commands read in it. One place for them (the root was computed in nine modules)."""
from pathlib import Path

#: the repository's root (this file is services/paths.py)
REPO = Path(__file__).resolve().parents[1]
#: the scenarios shipped with mfvs (the papers' experiments, the examples)
SCENARIOS = REPO / "examples" / "scenarios"
#: the deployment's files: profiles, TLS, install
DEPLOY = REPO / "deploy"
