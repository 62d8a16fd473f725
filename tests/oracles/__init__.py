"""Independent reference implementations the tests check the library against (test oracles).

They are not part of the library: they must never import the code they check.
"""
