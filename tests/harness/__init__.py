"""What tests (and `make edge-chain`) run that is not a benchmark: kept out of the wheel."""
