package com.tbp.agent.android;

import android.content.AttributionSource;
import android.content.Context;
import android.content.ContextWrapper;
import android.os.Build;
import java.lang.reflect.Field;

/**
 * The context the agent hands to CameraManager: the system context, presented as the shell's
 * package (com.android.shell, uid 2000), the one the services check the calling uid against. This
 * is how scrcpy's camera mirroring opens a camera from app_process (its FakeContext).
 */
final class FakeContext extends ContextWrapper {

    static final String PACKAGE_NAME = "com.android.shell";
    static final int SHELL_UID = 2000;

    private static FakeContext instance;

    private FakeContext(Context base) {
        super(base);
    }

    static synchronized FakeContext get() {
        if (instance == null) {
            instance = new FakeContext(Workarounds.systemContext());
        }
        return instance;
    }

    @Override
    public String getPackageName() {
        return PACKAGE_NAME;
    }

    @Override
    public String getOpPackageName() {
        return PACKAGE_NAME;
    }

    @Override
    public AttributionSource getAttributionSource() {
        return new AttributionSource.Builder(SHELL_UID).setPackageName(PACKAGE_NAME).build();
    }

    /** The default device (Android 14's virtual devices): the camera service asks for it. */
    public int getDeviceId() {
        return 0;
    }

    @Override
    public Context getApplicationContext() {
        return this;
    }

    /**
     * The system service, with this context in place of the system one where the service checks the
     * caller's package: ActivityManager does when CameraManager asks for the app's tasks (Android 16,
     * scrcpy #6523).
     */
    @Override
    public Object getSystemService(String name) {
        Object service = super.getSystemService(name);
        if (service != null && Context.ACTIVITY_SERVICE.equals(name) && Build.VERSION.SDK_INT >= 31) {
            try {
                Field field = service.getClass().getDeclaredField("mContext");
                field.setAccessible(true);
                field.set(service, this);
            } catch (ReflectiveOperationException e) {
                new LogcatLog().error("ActivityManager keeps the system context", e);
            }
        }
        return service;
    }
}
