"""The process shell every distributed role shares (`Role`, `WeightsIntake`); torch-free."""
