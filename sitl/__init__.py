"""The simulated vehicle and world: a stand-in for hardware in every test and demo."""
