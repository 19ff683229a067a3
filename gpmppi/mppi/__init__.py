"""mppi"""
