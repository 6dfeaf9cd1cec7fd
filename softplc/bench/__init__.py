"""Benchmark harness (`softplc bench`): engine scaling, scan timing, Modbus, online change."""
