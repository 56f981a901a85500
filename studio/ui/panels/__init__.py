"""The studio's panels, one module per tab of the control panel; each builds its GUI and refreshes it."""
