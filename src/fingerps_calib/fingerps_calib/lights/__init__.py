"""Light directions and LED positions from a shiny sphere (paper Sec. 3.1, Eq. 8-10)."""
