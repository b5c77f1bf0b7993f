"""The simulated world of the cell: parts on a table, a camera rendering them, an arm acting on them."""
