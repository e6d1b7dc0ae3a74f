package com.tbp.agent.android;

import android.util.Log;

/** The agent's log in logcat, tag {@value #TAG} ({@code adb logcat -s tbp-capture-agent}). */
final class LogcatLog implements com.tbp.agent.Log {

    static final String TAG = "tbp-capture-agent";

    @Override
    public void info(String message) {
        Log.i(TAG, message);
    }

    @Override
    public void error(String message, Throwable cause) {
        Log.e(TAG, message, cause);
    }
}
