"""methods (being assembled)"""
