"""misdirect"""
