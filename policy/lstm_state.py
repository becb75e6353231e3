"""The recurrent state every policy of a run hands back and forth: (h, c) of its LSTM, zeros at an episode's start."""

from __future__ import annotations

import numpy as np


class LstmState:
    """`initial_state` for a policy whose LSTM has `lstm_layers` layers of `hidden_size` cells."""

    lstm_layers: int
    hidden_size: int

    def initial_state(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Zero LSTM state (h, c) for n episodes, each (layers, n, hidden) float32."""
        shape = (self.lstm_layers, n, self.hidden_size)
        return np.zeros(shape, np.float32), np.zeros(shape, np.float32)
