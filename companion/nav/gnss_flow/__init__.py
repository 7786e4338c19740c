"""GNSS + optic-flow attitude for fixed wings (issue 15; Roberts, Walker, O'Shea 2005)."""
