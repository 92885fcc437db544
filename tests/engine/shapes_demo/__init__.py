"""Shape packages that live outside engine/ and are registered at run time (engine.shapes.register)."""
